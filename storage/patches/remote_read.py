"""Some patches of a tile on a bucket, read by byte ranges of its tables instead of downloading them.

A repair region reads its zone and context patches, a few dozen of a tile's thousands: on a work dir on a
bucket (:mod:`storage.objstore.mirror`) :func:`open_for_patches` opens the tile's points and faces tables
over ranged GETs of their recorded objects (the Parquet footer, then only the row groups the patches' rows
lie in: :class:`storage.patches.read.PatchStore` reads by row groups), so nothing is downloaded whole and
nothing is held on scratch. The regions of a repair batch share tiles; once this process has fetched
:func:`ranged_max_share` of a table's bytes by ranges, later opens download it whole (through the node's
cache) instead, so a tile costs at most (1 + that share) x its size however many regions read it. A table the
node's cache holds whole is copied from it. Locally (or for a file already downloaded), and by default (the
share is 0), it is the ordinary store.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from storage import recorded
from storage.patches.ranges import RangeFile
from storage.patches.read import PatchStore
from storage.patches.schema import FACES_FILE, POINTS_FILE


def ranged_max_share() -> float:
    """``MS3D_RANGED_SHARE``: the share of a table's bytes a process fetches by ranges before it downloads the
    table whole; default 0 (off): on the demo campus, whose repairs are dense (216 regions over 7 tiles), 0.5
    made the S3 run 1.37x the local one against 1.21-1.25x without (docs/benchmarks.md). Worth it where
    regions are few per tile (a good production with a few defects)."""
    try:
        return max(0.0, float(os.environ.get("MS3D_RANGED_SHARE", "0") or 0))
    except ValueError:
        return 0.0


_FETCHED: dict[str, int] = {}  # object key -> bytes this process fetched of it by ranges
_LOCK = threading.Lock()


class _CountedRangeFile(RangeFile):
    """A :class:`RangeFile` that adds what it fetches to the process's count per object."""

    def readinto(self, b) -> int:
        n = super().readinto(b)
        with _LOCK:
            _FETCHED[self.key] = _FETCHED.get(self.key, 0) + n
        return n


def fetched_by_range(key: str) -> int:
    """Bytes of the object ``key`` this process fetched by ranges so far."""
    with _LOCK:
        return _FETCHED.get(key, 0)


def open_for_patches(tile_dir: str | Path) -> PatchStore:
    """A :class:`PatchStore` of ``tile_dir`` for reading some of its patches (see the module docstring)."""
    tile_dir, share = Path(tile_dir), ranged_max_share()
    sources = {}
    for name in (POINTS_FILE, FACES_FILE) if share > 0 else ():
        obj = recorded.remote_object(tile_dir / name)
        if obj is None:
            continue
        store, key, size = obj
        if fetched_by_range(key) < share * size:
            sources[name] = _CountedRangeFile(store, key, size)
    return PatchStore(tile_dir, sources=sources)


__all__ = ["fetched_by_range", "open_for_patches", "ranged_max_share"]
