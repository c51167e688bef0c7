"""Compiled (numba) per-pair loops of the classify cues, over a batch's pairs concatenated.

The pairs of a cue batch are contiguous runs of rows (pair 0's rows, then pair 1's, ...). Each kernel walks
the runs once instead of building whole-batch keys or calling numpy once per pair:

- :func:`subset_runs`: the ``keep`` rows of smallest splitmix64 hash of their float64 coordinates, per
  run, in hash order (``ms3d_model.hashing.order_free_subset`` of every pair in one pass);
- :func:`run_covariances`: every run's mean and sample covariance, summed in row order like
  ``np.bincount``.

``benchmarks/kernel_bench.py`` times each against the numpy code it replaced. ``cache=True``: compiled once
per machine into ``__pycache__``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["nearest_distance_runs", "run_covariances", "run_starts", "subset_runs"]


def run_starts(counts: np.ndarray) -> np.ndarray:
    """(G + 1,) int64 offsets of runs of ``counts`` (G,) rows: run g is rows [start[g], start[g + 1])."""
    return np.concatenate([[0], np.cumsum(np.asarray(counts, np.int64))]).astype(np.int64)


@njit(cache=True, nogil=True)
def _splitmix64(z: np.uint64) -> np.uint64:
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@njit(cache=True, nogil=True)
def _hash_run(bits: np.ndarray, a: int, b: int, seed: np.uint64) -> np.ndarray:
    """(b - a,) uint64 hash of rows a..b of ``bits`` (n, 3) uint64: h = seed, then h = splitmix64(h ^ column)
    per column (``ms3d_model.hashing.order_free_subset``'s hash)."""
    h = np.empty(b - a, np.uint64)
    for i in range(a, b):
        z = seed
        for c in range(3):
            z = _splitmix64(z ^ bits[i, c])
        h[i - a] = z
    return h


@njit(cache=True, nogil=True)
def subset_runs(bits: np.ndarray, seeds: np.ndarray, start: np.ndarray, keep: int) -> np.ndarray:
    """(k,) int64 rows of ``order_free_subset`` per run of ``start`` (G + 1,): all its rows in order when it
    has at most ``keep``, else the ``keep`` rows of smallest hash (seeded by ``seeds`` (G,) uint64) in
    ascending hash, a tie in row order. bits: (n, 3) uint64, the float64 coordinates viewed as integers.

    The hashes are uniform, so the ``keep`` smallest lie below about keep / n of their range: only the rows
    under a threshold a few standard deviations above that are sorted (the threshold doubles until at
    least ``keep`` rows are under it), not the whole run."""
    total = 0
    for g in range(len(start) - 1):
        total += min(keep, start[g + 1] - start[g])
    out = np.empty(total, np.int64)
    k = 0
    for g in range(len(start) - 1):
        a, b = start[g], start[g + 1]
        if b - a <= keep:
            for i in range(a, b):
                out[k] = i
                k += 1
            continue
        h = _hash_run(bits, a, b, seeds[g])
        frac = (keep + 4.0 * np.sqrt(keep) + 16.0) / (b - a)
        while True:
            if frac >= 1.0:
                cand = np.arange(b - a)
                break
            t = np.uint64(frac * 18446744073709551616.0)
            cand = np.flatnonzero(h < t)
            if len(cand) >= keep:
                break
            frac *= 2.0
        order = np.argsort(h[cand], kind="mergesort")  # stable: a tie (identical points) keeps row order
        for j in range(keep):
            out[k] = a + cand[order[j]]
            k += 1
    return out


@njit(cache=True, nogil=True)
def run_covariances(p: np.ndarray, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per run of ``start`` (G + 1,) over the points ``p`` (n, 3) float64: (G, 3) mean and (G, 3, 3) sample
    covariance (divided by max(count - 1, 1)); sums run in row order, as ``np.bincount``'s do."""
    b = len(start) - 1
    mean = np.zeros((b, 3))
    cov = np.zeros((b, 3, 3))
    for g in range(b):
        a, e = start[g], start[g + 1]
        n = e - a
        for c in range(3):
            s = 0.0
            for i in range(a, e):
                s += p[i, c]
            mean[g, c] = s / n
        for i in range(3):
            for j in range(i, 3):
                s = 0.0
                for r in range(a, e):
                    s += (p[r, i] - mean[g, i]) * (p[r, j] - mean[g, j])
                cov[g, i, j] = s / max(n - 1, 1)
                cov[g, j, i] = cov[g, i, j]
    return mean, cov


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
        if d2 < best:
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
                ci[c] = min(max(int(math.floor((q[j, c] - lo[c]) / h)), 0), dims[c] - 1)
            best = np.inf
            r = 0
            while True:
                if r > MAX_RINGS:  # far from the points, or a cell size that does not suit them: all of them
                    for i in range(a, e):
                        dx, dy, dz = qx - p[i, 0], qy - p[i, 1], qz - p[i, 2]
                        d2 = dx * dx + dy * dy + dz * dz
                        if d2 < best:
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
