"""Routing rows to ground tiles (vectorised), and boxes under a transform.

A tile (ix, iy) covers ``[ix*s, (ix+1)*s) x [iy*s, (iy+1)*s)`` in world metres (``storage.grid``). Rows
are routed by the tile of their *patch centre* (``PatchGrid.tile_of_cells``), so a patch is never split
between tiles.
"""

from __future__ import annotations

import numpy as np

from storage.ids import TileId


def group_by_tile(tile_ij: np.ndarray) -> list[tuple[TileId, np.ndarray]]:
    """tile_ij: (n, 2) int -> [(tile, row indices (k,) int64 ascending)], tiles in sorted order.

    One stable argsort over packed keys; no Python loop over rows.
    """
    if len(tile_ij) == 0:
        return []
    t = np.asarray(tile_ij, dtype=np.int64)
    key = ((t[:, 0] + (1 << 30)) << 31) | (t[:, 1] + (1 << 30))  # tile indices |i| < 2**30
    order = np.argsort(key, kind="stable")
    ks = key[order]
    cut = np.flatnonzero(np.diff(ks)) + 1
    starts = np.concatenate([[0], cut])
    stops = np.concatenate([cut, [len(ks)]])
    out = []
    for a, b in zip(starts, stops):  # one iteration per tile, not per row
        ij = t[order[a]]
        out.append((TileId(int(ij[0]), int(ij[1])), order[a:b]))
    return out


def transform_bounds(matrix: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The axis-aligned box of the 8 corners of [lo, hi] mapped by the 4x4 ``matrix``."""
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    m = np.asarray(matrix, float)
    c = corners @ m[:3, :3].T + m[:3, 3]
    return c.min(axis=0), c.max(axis=0)
