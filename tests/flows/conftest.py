"""Fixtures of the flow tests: the hand-made three-region campus of :mod:`synth.handmade`."""

from __future__ import annotations

import pytest

from synth.handmade import ORIGIN, REGIONS, build_campus, region_mesh  # noqa: F401 - re-exported for tests


@pytest.fixture
def handmade_campus(tmp_path):
    """Factory: build_campus(root=tmp_path, **kw) -> config path."""
    return lambda **kw: build_campus(tmp_path, **kw)
