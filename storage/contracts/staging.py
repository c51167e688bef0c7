"""The staging-file contract between ingest and partition.

Ingest routes each unit's rows to the ground tiles they belong to as sorted runs
``staging/{tile}/{unit key}-{part:03d}.arrow`` (``storage.contracts.columns.write_run``); partition reads a tile's
runs. A unit key is the input's identity, never a list position: ``{m|p}{source:08x}-{fp[:8]}-{range:05d}``
(mesh or points, stable source id of the path, content fingerprint, range number), so the set of staging
files is a function of the inputs. :func:`prune_staging` removes every file whose unit the current plan
does not name, and a tile's :func:`staging_fingerprint` changes exactly when the set of files feeding
it does.

    >>> unit_key("mesh", 7, "0123456789abcdef", 0), run_name("p0000002a-deadbeef-00003", 1)
    ('m00000007-01234567-00000', 'p0000002a-deadbeef-00003-001.arrow')
"""

from __future__ import annotations

import contextlib
from pathlib import Path

from storage import recorded
from storage.atomic import file_fingerprint
from storage.contracts.columns import RUN_SUFFIX
from storage.workdir.layout import WorkDir

FACE_VERTEX_COLUMNS = ("x0", "y0", "z0", "x1", "y1", "z1", "x2", "y2", "z2")  # face corners, campus-local m


def unit_key(kind: str, source: int, fp: str, part: int) -> str:
    """The key of an ingest unit: kind ("mesh" | "points"), source id, content fingerprint, range number."""
    return f"{'m' if kind == 'mesh' else 'p'}{source:08x}-{fp[:8]}-{part:05d}"


def run_name(key: str, part: int) -> str:
    """File name of run ``part`` of unit ``key`` (one per chunk of a point range; meshes have part 0)."""
    return f"{key}-{part:03d}{RUN_SUFFIX}"


def is_point_run(path: Path) -> bool:
    """Whether a staging run holds points (else mesh faces), from its unit key."""
    return path.name.startswith("p")


def staged_files(wd: WorkDir, tile_key: str) -> list[Path]:
    """The complete staging runs of a tile (temporary names excluded), sorted by name (on a bucket: the recorded
    runs, downloaded or not: :mod:`storage.recorded`)."""
    d = wd.root / "staging" / tile_key
    return [p for p in recorded.glob(d, f"*{RUN_SUFFIX}") if not p.name.startswith(".")]


def staging_fingerprint(parts: list[Path]) -> list[str]:
    """``name:content fingerprint`` of each staging run of a tile (a tile's partition input)."""
    return [f"{p.name}:{file_fingerprint(p)}" for p in parts]


def remove_unit_runs(wd: WorkDir, key: str) -> None:
    """Remove every staging run of unit ``key`` (a redone unit starts clean)."""
    for old in recorded.glob(wd.root / "staging", f"*/{key}-*{RUN_SUFFIX}"):
        recorded.unlink(old)


def prune_staging(wd: WorkDir, keys: set[str]) -> int:
    """Remove staging files of units not in ``keys`` (and temporary files); returns how many."""
    root = wd.root / "staging"
    removed = 0
    for d in recorded.children(root):
        if not recorded.is_dir(d):
            continue
        for f in recorded.children(d):
            if f.name.startswith(".") or not f.name.endswith(RUN_SUFFIX) or f.name.rsplit("-", 1)[0] not in keys:
                recorded.unlink(f)
                removed += 1
        with contextlib.suppress(OSError):
            d.rmdir()  # only when empty
    return removed
