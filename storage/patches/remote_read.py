"""Some patches of a tile on a bucket, read by byte ranges of its tables instead of downloading them.

A repair region reads its zone and context patches, a few dozen of a tile's thousands: on a work dir on a
bucket (:mod:`storage.objstore.mirror`) :func:`open_for_patches` opens the tile's points and faces tables
over ranged GETs of their recorded objects (the Parquet footer, then only the row groups the patches' rows
lie in: :class:`storage.patches.read.PatchStore` reads by row groups), so nothing is downloaded whole and
nothing is held on scratch. The regions of a repair batch share tiles; once this process has fetched
``RANGED_MAX_SHARE`` of a table's bytes by ranges, later opens download it whole (through the node's cache)
instead, so a tile costs at most about 1.5x its size however many regions read it. Locally (or for a file
already downloaded) it is the ordinary store.
"""

from __future__ import annotations

import threading
from pathlib import Path

from storage import recorded
from storage.patches.ranges import RangeFile
from storage.patches.read import PatchStore
from storage.patches.schema import FACES_FILE, POINTS_FILE

RANGED_MAX_SHARE = 0.5
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
    tile_dir = Path(tile_dir)
    sources = {}
    for name in (POINTS_FILE, FACES_FILE):
        obj = recorded.remote_object(tile_dir / name)
        if obj is None:
            continue
        store, key, size = obj
        if fetched_by_range(key) < RANGED_MAX_SHARE * size:
            sources[name] = _CountedRangeFile(store, key, size)
    return PatchStore(tile_dir, sources=sources)


__all__ = ["RANGED_MAX_SHARE", "fetched_by_range", "open_for_patches"]
