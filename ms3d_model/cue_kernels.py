"""Compiled (numba) per-pair loops of the classify cues, over a batch's pairs concatenated.

The pairs of a cue batch are contiguous runs of rows (pair 0's rows, then pair 1's, ...). Each kernel walks
the runs once instead of building whole-batch keys or calling numpy once per pair:

- :func:`subset_runs`: the rows of smallest splitmix64 hash of their float64 coordinates, per run, in hash
  order (``ms3d_model.hashing.order_free_subset`` of every pair, at two sizes, in one pass);
- nearest rows within a run come from :mod:`ms3d_model.grid_search`;
- :func:`run_covariances`: every run's mean and sample covariance, summed in row order like
  ``np.bincount``.

``benchmarks/kernel_bench.py`` times each against the numpy code it replaced. ``cache=True``: compiled once
per machine into ``__pycache__``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["run_covariances", "run_starts", "subset_runs"]


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
def _smallest(h: np.ndarray, keep: int) -> np.ndarray:
    """(keep,) int64 positions of the ``keep`` smallest of the uniform hashes ``h`` (n,) uint64 (keep < n), in
    ascending hash, a tie in position order. Only the hashes under a threshold a few standard deviations
    above keep / n of their range are sorted (it doubles until at least ``keep`` are under it)."""
    frac = (keep + 4.0 * np.sqrt(keep) + 16.0) / len(h)
    while True:
        if frac >= 1.0:
            cand = np.arange(len(h))
            break
        cand = np.flatnonzero(h < np.uint64(frac * 18446744073709551616.0))
        if len(cand) >= keep:
            break
        frac *= 2.0
    order = np.argsort(h[cand], kind="mergesort")  # stable: a tie (identical points) keeps row order
    return cand[order[:keep]]


@njit(cache=True, nogil=True)
def subset_runs(bits: np.ndarray, seeds: np.ndarray, start: np.ndarray, keep: int, keep_large: int
                ) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ``order_free_subset`` per run of ``start`` (G + 1,), for two sizes ``keep`` <= ``keep_large``:
    (rows (k1,) int64, rows (k2,) int64). A run of at most that many rows gives all of them in order, a larger
    one the rows of smallest hash (seeded by ``seeds`` (G,) uint64) in ascending hash, a tie in row order.
    bits: (n, 3) uint64, the float64 coordinates viewed as integers.

    Each run is hashed once: the ``keep`` smallest hashes are the first ``keep`` of the ``keep_large``
    smallest."""
    k1 = k2 = 0
    for g in range(len(start) - 1):
        k1 += min(keep, start[g + 1] - start[g])
        k2 += min(keep_large, start[g + 1] - start[g])
    small = np.empty(k1, np.int64)
    large = np.empty(k2, np.int64)
    i1 = i2 = 0
    for g in range(len(start) - 1):
        a, b = start[g], start[g + 1]
        n = b - a
        if n > keep:
            h = _hash_run(bits, a, b, seeds[g])
            pick = _smallest(h, keep_large) if n > keep_large else _smallest(h, keep)
            for j in range(keep):
                small[i1 + j] = a + pick[j]
            if n > keep_large:
                for j in range(keep_large):
                    large[i2 + j] = a + pick[j]
        else:
            for j in range(n):
                small[i1 + j] = a + j
        if n <= keep_large:
            for j in range(n):
                large[i2 + j] = a + j
        i1 += min(keep, n)
        i2 += min(keep_large, n)
    return small, large


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
