"""Bad inputs end in one clear line, the right exit code, and nothing lost (a sample of the cases of
``benchmarks/bad_inputs.py``, which prints the whole table)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "bad_inputs.py"


def _bench():
    spec = importlib.util.spec_from_file_location("bad_inputs", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


BAD = _bench()
BAD.LATER_STAGES = False  # the later stages have their own tests; every case here fails before them
SAMPLE = ["truncated-laz", "zero-byte-laz", "stray-file", "missing-texture", "bad-index", "geographic-crs",
          "mesh-10km-off", "config-typo", "full-disk"]


@pytest.mark.parametrize("name", SAMPLE)
def test_bad_input(name, tmp_path, monkeypatch):
    monkeypatch.setattr(BAD, "LATER_STAGES", name == "full-disk")  # only a full disk needs every stage's outputs
    case = next(c for c in BAD.CASES if c.name == name)
    result = BAD.run_case(case, tmp_path)
    assert BAD.check(result) == [], (result["stderr"], result["stdout"][-2000:])


def test_the_table_has_at_least_20_kinds():
    assert len(BAD.CASES) >= 20 and len({c.name for c in BAD.CASES}) == len(BAD.CASES)
