"""A tile store's identity and the grades of its patches: one definition each, for every stage.

- :func:`store_fingerprint` is what a later stage records to know whether the partition output (and the
  side tables it reads) changed since it ran. Partition rewrites all three tables (``patches.parquet``
  last), so sizes and modification times identify a rewrite without reading the data.
- :func:`patch_grades` says which patches are bad, for the regions stage (what to rebuild) and for the
  merge (what to replace) alike, under ``repair.grades``. Two readers of one rule cannot disagree.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import file_sha256
from storage.contracts.tile_mesh import GRADE_UNKNOWN
from storage.patches.schema import FACES_FILE, PATCHES_FILE, POINTS_FILE, side_table_path
from storage.workdir.manifest import combine_fingerprints

STORE_TABLES = (PATCHES_FILE, POINTS_FILE, FACES_FILE)
GRADE_GOOD, GRADE_BAD = 0, 1
GRADE_MODES = ("auto", "model", "labels", "all")
_GRADE_TABLES = {"auto": ("grades", "labels"), "model": ("grades",), "labels": ("labels",), "all": ()}


def store_fingerprint(tile_dir: str | Path, sides: tuple[str, ...] = ()) -> str:
    """Identity of a tile's partition output plus the named side tables (``"labels"``, ``"grades"``).

    A missing file enters as ``name:-``, so a store that lost (or gained) a table changes identity;
    a tile with no store at all fingerprints as ``"missing"``.
    """
    tile_dir = Path(tile_dir)
    if not recorded.is_file(tile_dir / PATCHES_FILE):
        return "missing"
    paths = [tile_dir / n for n in STORE_TABLES] + [side_table_path(tile_dir, s) for s in sides]
    parts = []
    for p in paths:
        st = recorded.state(p)  # a work dir on a bucket: what the records say, nothing downloaded
        parts.append(f"{p.name}:{st.size}:{st.mtime_ns}" if st is not None else f"{p.name}:-")
    return combine_fingerprints(parts)


def _tables(mode: str) -> tuple[str, ...]:
    if mode not in GRADE_MODES:
        raise ValueError(f"grades mode must be one of {GRADE_MODES}, got {mode!r}")
    return _GRADE_TABLES[mode]


def grades_identity(tile_dir: str | Path, mode: str) -> str:
    """What :func:`patch_grades` of the tile's store depends on besides the patches table: ``"all"``, the
    name and sha256 of the side table it reads (``"labels:<hex>"``), or ``"none"``. A result built on the
    grades of one identity is valid for every mode of the same identity."""
    if mode == "all":
        return "all"
    for name in _tables(mode):
        p = side_table_path(tile_dir, name)
        if recorded.is_file(p):
            return f"{name}:{file_sha256(p)}"
    return "none"


def patch_grades(store, mode: str = "auto") -> tuple[np.ndarray, np.ndarray, str]:
    """Grades of a tile's patches under ``repair.grades``: ((u,) int64 patch keys, (u,) int8 grade, source).

    grade is -1 unknown / 0 good / 1 bad. ``mode`` "auto": the classify stage's ``grades`` side table when
    present, else ``labels``; "model" / "labels": only that table; "all": every patch is bad (fusion
    everywhere the MLS reaches). source is "grades", "labels", "all" or "none" (every patch unknown).
    ``store`` is a :class:`storage.patches.read.PatchStore` (or a ``PatchTable``: the patches and side tables).
    """
    tables = _tables(mode)
    keys = store.patches()["patch"]
    if mode == "all":
        return keys, np.full(len(keys), GRADE_BAD, np.int8), "all"
    for name in tables:
        side = store.side(name)
        if side is not None:
            col = side["grade"] if name == "grades" else side["label"]
            return keys, np.asarray(col, np.int8), name
    return keys, np.full(len(keys), GRADE_UNKNOWN, np.int8), "none"
