"""The vertex-id namespace of the campus mesh (int64), shared by ingest, repair and merge.

- ``>= 0``: an input vertex, ``source << 32 | index`` (:mod:`tasks.ingest`);
- ``[SPLIT_MIN, -2]``: a vertex made by splitting a long face at ingest, a hash of the edge's two ids
  (:func:`tasks.geometry.split.split_vertex_id`): a campus id like the others, shared by every tile;
- ``-1`` (:data:`MISSING`): a store written without ids (corners then weld by exact position);
- ``<= LOCAL_BASE``: ids local to one region or one merge (new MLS vertices, seam vertices moved,
  position keys, a merge's keys of a rebuilt region's own vertices: ``(rank of the region in the merge) << 32
  | index``), in blocks of 2**58 so the kinds never meet: :func:`local_ids`.

A campus id welds across tiles and regions; a local id never leaves the unit that made it.

>>> import numpy as np
>>> is_campus_id(np.array([5, -1, -7, local_ids(np.arange(1), 0)[0]])).tolist()
[True, False, True, False]
"""

from __future__ import annotations

import numpy as np

MISSING = -1
SPLIT_MIN = -(1 << 62) - 1
LOCAL_BASE = -(1 << 62) - 2
_BLOCK = 1 << 58
BLOCKS = {"rebuilt": 0, "seam": 1, "region_position": 2, "merge_position": 3, "free": 4, "merge_own": 5}


def is_campus_id(ids: np.ndarray) -> np.ndarray:
    """(n,) bool: ids that name a campus vertex (an input vertex or a split vertex)."""
    ids = np.asarray(ids, np.int64)
    return (ids >= 0) | ((ids <= -2) & (ids >= SPLIT_MIN))


def local_ids(index: np.ndarray, block: int | str) -> np.ndarray:
    """(n,) int64 local ids of ``index`` (n,) int >= 0 in ``block`` (a name of :data:`BLOCKS` or 0..15)."""
    b = BLOCKS[block] if isinstance(block, str) else int(block)
    return np.int64(LOCAL_BASE) - np.int64(b) * np.int64(_BLOCK) - np.asarray(index, np.int64)


__all__ = ["BLOCKS", "LOCAL_BASE", "MISSING", "SPLIT_MIN", "is_campus_id", "local_ids"]
