"""Nearest rows within runs of rows by a uniform grid per run (numba), where building k-d trees cost more.

The rows of a cue batch come as contiguous runs, one per pair (pair 0's rows, then pair 1's, ...), and a
neighbour must come from the query's own run. A grid per run is built in linear time (a counting sort of
the rows by cell) and searched in rings of cells around the query's cell, until no cell outside the rings
can hold a nearer row (their distance bound exceeds the best so far, with 1e-9 relative slack for the cells'
rounding). A query far from its run's rows (more than ``MAX_RINGS`` rings) compares every row.

:func:`nearest_distance_runs` gives the distance to the nearest row: the classify mesh -> point distances,
~38 M points per real-density tile and a few hundred queries per pair, where building the trees was the
cost. (A grid k-nearest search for the point -> mesh candidates, k = 8 of ~100 face centres per pair, was
no faster than a k-d tree per pair, nor was comparing them all: neither is kept.)

Distances are the float64 sums (dx² + dy²) + dz² a k-d tree computes, so the same values.
``benchmarks/cue_kernel_bench.py`` times them against the k-d trees they replaced.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["MAX_RINGS", "nearest_distance_runs"]


MAX_RINGS = 6  # rings of cells searched around a query before it compares every point of its run


@njit(cache=True, nogil=True)
def _grid(p: np.ndarray, a: int, e: int):
    """A uniform grid over rows a..e of p (n, 3): (origin (3,), cell size, dims (3,), cell start
    (cells + 1,), rows sorted by cell). The cell size aims at ~4 points per occupied cell of a surface
    (its area taken as the two largest extents' product), with at most ~4 cells per point."""
    n = e - a
    lo = np.empty(3)
    ext = np.empty(3)
    for c in range(3):
        mn, mx = p[a, c], p[a, c]
        for i in range(a, e):
            mn = min(mn, p[i, c])
            mx = max(mx, p[i, c])
        lo[c], ext[c] = mn, mx - mn
    s = np.sort(ext)
    h = math.sqrt(4.0 * max(s[2] * s[1], 1e-12) / n)
    if h <= 0.0 or not math.isfinite(h):
        h = 1.0
    dims = np.empty(3, np.int64)
    while True:
        total = 1
        for c in range(3):
            dims[c] = int(ext[c] / h) + 1
            total *= dims[c]
        if total <= 4 * n + 64:
            break
        h *= 1.25
    cell = np.empty(n, np.int64)
    start = np.zeros(total + 1, np.int64)
    for i in range(a, e):
        ix = min(int((p[i, 0] - lo[0]) / h), dims[0] - 1)
        iy = min(int((p[i, 1] - lo[1]) / h), dims[1] - 1)
        iz = min(int((p[i, 2] - lo[2]) / h), dims[2] - 1)
        cell[i - a] = (ix * dims[1] + iy) * dims[2] + iz
        start[cell[i - a] + 1] += 1
    for j in range(total):
        start[j + 1] += start[j]
    fill = start[:-1].copy()
    rows = np.empty(n, np.int64)
    for i in range(n):
        rows[fill[cell[i]]] = a + i
        fill[cell[i]] += 1
    return lo, h, dims, start, rows


@njit(cache=True, nogil=True)
def _cell_min(p, rows, start, cell, qx, qy, qz, best):
    for r in range(start[cell], start[cell + 1]):
        i = rows[r]
        dx, dy, dz = qx - p[i, 0], qy - p[i, 1], qz - p[i, 2]
        d2 = dx * dx + dy * dy + dz * dz
        if d2 < best:  # noqa: PLR1730 - explicit: a NaN distance never wins
            best = d2
    return best


@njit(cache=True, nogil=True)
def nearest_distance_runs(p: np.ndarray, p_start: np.ndarray, q: np.ndarray, q_start: np.ndarray) -> np.ndarray:
    """(m,) float64 distance from each row of ``q`` (m, 3) float64 to the nearest row of ``p`` (n, 3) float64
    of the same run (runs: ``p_start`` / ``q_start`` (G + 1,)); inf for a run without points. What a k-d
    tree per run gives (the same float64 squared sums, so the same distances), without building the
    trees: a grid per run, searched in rings of cells around the query's cell until no unvisited cell can
    hold a nearer point."""
    out = np.full(len(q), np.inf)
    for g in range(len(p_start) - 1):
        a, e = p_start[g], p_start[g + 1]
        if e == a or q_start[g + 1] == q_start[g]:
            continue
        lo, h, dims, start, rows = _grid(p, a, e)
        for j in range(q_start[g], q_start[g + 1]):
            qx, qy, qz = q[j, 0], q[j, 1], q[j, 2]
            ci = np.empty(3, np.int64)
            for c in range(3):
                ci[c] = min(max(int(math.floor((q[j, c] - lo[c]) / h)), 0), dims[c] - 1)  # noqa: RUF046
            best = np.inf
            r = 0
            while True:
                if r > MAX_RINGS:  # far from the points, or a cell size that does not suit them: all of them
                    for i in range(a, e):
                        dx, dy, dz = qx - p[i, 0], qy - p[i, 1], qz - p[i, 2]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best:  # noqa: PLR1730 - explicit: a NaN distance never wins
                            best = d2
                    break
                for ix in range(max(ci[0] - r, 0), min(ci[0] + r, dims[0] - 1) + 1):
                    for iy in range(max(ci[1] - r, 0), min(ci[1] + r, dims[1] - 1) + 1):
                        shell = abs(ix - ci[0]) == r or abs(iy - ci[1]) == r
                        for iz in range(max(ci[2] - r, 0), min(ci[2] + r, dims[2] - 1) + 1):
                            if shell or abs(iz - ci[2]) == r:
                                best = _cell_min(p, rows, start, (ix * dims[1] + iy) * dims[2] + iz, qx, qy, qz, best)
                # every point outside the cells within r of ci is at least this far (sides past the grid
                # hold none)
                bound = np.inf
                for c in range(3):
                    if ci[c] - r > 0:
                        bound = min(bound, q[j, c] - (lo[c] + (ci[c] - r) * h))
                    if ci[c] + r < dims[c] - 1:
                        bound = min(bound, lo[c] + (ci[c] + r + 1) * h - q[j, c])
                if bound == np.inf or (best < np.inf and math.sqrt(best) < bound * (1.0 - 1e-9) - 1e-9):
                    break
                r += 1
            out[j] = math.sqrt(best)
    return out
