"""Regions: connected sets of bad patches, the unit of repair.

Components of a set of patch keys under the 26-neighbourhood of the global,
world-anchored grid, growth, ring of context cells, and splitting of regions larger than a memory
budget. Keys are global (:class:`storage.grid.PatchGrid`), so a region that spans a tile border or a
tile corner is one region, with no border special case: tiles only matter when a region is read.

No I/O here: :mod:`tasks.regions.stage` reads the grades and writes the plan
(:mod:`storage.contracts.region_plan`, which also holds the :class:`Region` record).

Region identity: ``Region.key`` is ``"r"`` + the hex of the smallest patch key of its rebuilt set
(stable across runs: a region keeps its folder and manifest unit while it keeps its first patch);
``Region.number`` is a stable 31-bit number (crc32 of the key) for per-face provenance arrays.

    >>> import numpy as np
    >>> from storage.grid import PatchGrid
    >>> keys = PatchGrid.pack(np.array([[0, 0, 0], [1, 1, 1], [5, 0, 0], [2, 2, 2]]))
    >>> connected_components(keys).tolist()   # (1,1,1) touches (0,0,0) and (2,2,2) by a corner
    [0, 0, 1, 0]
"""

from __future__ import annotations

import zlib

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components as _cc

from storage.contracts.region_plan import Region
from storage.grid import PatchGrid

# working set of a region per thinned MLS point / mesh face / raw MLS point (fusion graph, normals,
# k-NN, charts, Delaunay): least squares over 79 demo regions' tracemalloc peaks (numpy and Python
# allocations; open3d's own buffers are not traced). MLS points beyond ~8 per face are thinned away.
BYTES_PER_POINT = 4000
BYTES_PER_FACE = 6600
BYTES_PER_RAW_POINT = 50
THINNED_POINTS_PER_FACE = 8


def patch_cost_bytes(n_points: np.ndarray, n_faces: np.ndarray) -> np.ndarray:
    """Estimated working set of each patch in a region: (u,) int counts -> (u,) float64 bytes."""
    p, f = np.asarray(n_points, np.float64), np.asarray(n_faces, np.float64)
    return BYTES_PER_POINT * np.minimum(p, THINNED_POINTS_PER_FACE * f) + BYTES_PER_FACE * f + BYTES_PER_RAW_POINT * p


_OFFSETS_26 = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)
                        if (a, b, c) != (0, 0, 0)], dtype=np.int64)
_HALF_13 = _OFFSETS_26[[tuple(o) > (0, 0, 0) for o in _OFFSETS_26.tolist()]]


def _neighbour_pairs(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs (a, b) of keys that are 26-neighbours. keys: (n,) int64 sorted unique."""
    ijk = PatchGrid.unpack(keys)
    a_all, b_all = [], []
    for off in _HALF_13:
        nb = PatchGrid.pack(ijk + off)
        pos = np.searchsorted(keys, nb)
        pos[pos >= len(keys)] = 0
        hit = keys[pos] == nb if len(keys) else np.zeros(0, bool)
        a_all.append(np.flatnonzero(hit))
        b_all.append(pos[hit])
    return np.concatenate(a_all), np.concatenate(b_all)


def connected_components(keys: np.ndarray) -> np.ndarray:
    """Component label of each patch key under the 26-neighbourhood.

    keys: (n,) int64 packed patch keys (any order, unique). Returns (n,) int64 labels 0..c-1,
    numbered in the order of each component's smallest key.
    """
    keys = np.asarray(keys, dtype=np.int64)
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(keys)
    sk = keys[order]
    if len(np.unique(sk)) != len(sk):
        raise ValueError("patch keys must be unique")
    a, b = _neighbour_pairs(sk)
    n = len(sk)
    g = coo_matrix((np.ones(len(a), np.int8), (a, b)), shape=(n, n))
    _, lab = _cc(g, directed=False)
    # renumber by the smallest key of each component (sk is ascending: first occurrence order)
    first = np.unique(lab, return_index=True)[1]
    remap = np.empty(len(first), np.int64)
    remap[lab[np.sort(first)]] = np.arange(len(first))
    out = np.empty(n, np.int64)
    out[order] = remap[lab]
    return out


def dilate(keys: np.ndarray, cells: int, within: np.ndarray | None = None) -> np.ndarray:
    """Keys within ``cells`` steps (26-neighbourhood, i.e. Chebyshev distance) of ``keys``.

    keys: (n,) int64. within: optional (m,) int64 keys the result is restricted to (e.g. the patches
    that exist). Returns sorted unique int64 keys, ``keys`` included.
    """
    keys = np.unique(np.asarray(keys, np.int64))
    if cells <= 0 or len(keys) == 0:
        out = keys
    else:
        r = np.arange(-cells, cells + 1)
        offs = np.stack(np.meshgrid(r, r, r, indexing="ij"), -1).reshape(-1, 3)
        ijk = PatchGrid.unpack(keys)
        out = np.unique(PatchGrid.pack((ijk[:, None, :] + offs[None]).reshape(-1, 3)))
    if within is not None:
        out = out[np.isin(out, within)]
    return out


def region_key(patches: np.ndarray) -> str:
    """A region's stable key: "r" + the 16 hex digits of its smallest patch key (two's complement)."""
    return f"r{int(np.min(patches)) & ((1 << 64) - 1):016x}"


def region_number(key: str) -> int:
    """A region's stable 31-bit number (crc32 of its key), for per-face provenance arrays."""
    return zlib.crc32(key.encode()) & 0x7FFFFFFF


def _split(keys: np.ndarray, cost: np.ndarray, budget: float) -> list[np.ndarray]:
    """Bisect ``keys`` at the median cell of the longest axis until each part's cost is <= budget."""
    if cost.sum() <= budget or len(keys) < 2:
        return [keys]
    ijk = PatchGrid.unpack(keys)
    ext = ijk.max(0) - ijk.min(0)
    axis = int(np.argmax(ext))
    c = ijk[:, axis]
    cut = np.median(c)
    left = c <= cut if (c <= cut).sum() < len(c) else c < cut
    if left.all() or not left.any():
        order = np.argsort(c, kind="stable")
        left = np.zeros(len(c), bool)
        left[order[: len(c) // 2]] = True
    return _split(keys[left], cost[left], budget) + _split(keys[~left], cost[~left], budget)


def plan_regions(bad_keys: np.ndarray, all_keys: np.ndarray, grid: PatchGrid, *, min_patches: int = 1,
                 grow_cells: int = 0, context_cells: int = 2, patch_cost: np.ndarray | None = None,
                 budget_bytes: float = float("inf")) -> list[Region]:
    """Regions of the bad patches.

    bad_keys: (b,) int64 keys graded bad. all_keys: (n,) int64 sorted keys of every existing patch
    (growth and context are restricted to them). patch_cost: (n,) estimated bytes per patch of
    ``all_keys`` (default 1). Components with fewer than ``min_patches`` bad patches are dropped; a
    component whose cost exceeds ``budget_bytes`` is split (bisection of the longest axis), and each
    part becomes a region with ``parent`` set. Returns regions sorted by key.
    """
    all_keys = np.asarray(all_keys, np.int64)
    bad = np.unique(np.asarray(bad_keys, np.int64))
    bad = bad[np.isin(bad, all_keys)]
    cost_all = np.ones(len(all_keys)) if patch_cost is None else np.asarray(patch_cost, np.float64)
    rebuilt = dilate(bad, grow_cells, within=all_keys)
    lab = connected_components(rebuilt)
    out = []
    for c in range(int(lab.max()) + 1 if len(lab) else 0):
        members = rebuilt[lab == c]
        nbad = int(np.isin(members, bad).sum())
        if nbad < min_patches:
            continue
        cost = cost_all[np.searchsorted(all_keys, members)]
        parts = _split(members, cost, budget_bytes)
        parent = region_key(members) if len(parts) > 1 else ""
        for part in parts:
            ctx = np.setdiff1d(dilate(part, context_cells, within=all_keys), part)
            key = region_key(part)
            tiles = np.unique(grid.tile_of_keys(np.concatenate([part, ctx])), axis=0)
            out.append(Region(key=key, number=region_number(key), patches=part, bad=part[np.isin(part, bad)],
                              context=ctx, tiles=tuple(f"{a}_{b}" for a, b in tiles.tolist()), parent=parent,
                              est_bytes=int(cost_all[np.searchsorted(all_keys, part)].sum())))
    return sorted(out, key=lambda r: r.key)
