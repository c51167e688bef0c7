"""The classify cues' compiled per-pair loops (``ms3d_model.cue_kernels``) against the numpy code they
replaced, side by side, on a classify batch of real density built here.

    .venv/bin/python benchmarks/cue_kernel_bench.py [--pairs 300] [--repeat 3]

Each row runs the numpy version (the code as it was before, kept here as the baseline: the same inputs, the
same outputs) and the function ms3d calls now, checks that both give the same answer, and prints the best of
``--repeat`` wall times.

Inputs: ``--pairs`` pairs of a cue batch, each a noisy 5 x 5 m wall patch of 3,000-40,000 points (a real
density tile's range) over 50-400 triangles.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from kernel_bench import run_cases

from ms3d_model.cue_kernels import run_covariances, run_starts, subset_runs
from ms3d_model.cues import _pair_knn
from ms3d_model.grid_search import nearest_distance_runs
from ms3d_model.hashing import order_free_subset
from ms3d_model.segments import sorted_segments

GAP = 1.0e6  # the old 4D trees' pair gap


def batch(pairs: int, seed: int = 0):
    """Points (n, 3), their counts (B,), faces' centres (m, 3), their counts (B,): the pairs as runs."""
    rng = np.random.default_rng(seed)
    pts, cen, n, m = [], [], [], []
    for g in range(pairs):
        k = int(rng.integers(3000, 40000))
        off = rng.uniform(0, 300, 3)
        pts.append(np.c_[rng.uniform(0, 5, (k, 2)), rng.normal(scale=0.01, size=k)] + off)
        f = int(rng.integers(50, 400))
        cen.append(np.c_[rng.uniform(0, 5, (f, 2)), np.zeros(f)] + off)
        n.append(k)
        m.append(f)
    return np.concatenate(pts), np.array(n), np.concatenate(cen), np.array(m)


def lifted(xyz, counts):
    return np.c_[xyz, np.repeat(np.arange(len(counts)), counts) * GAP]


# --------------------------------------------------------------------- the numpy code before the kernels

def subsets_numpy(p, counts, seeds, cap):
    out, start = [], run_starts(counts)
    for g, s in enumerate(seeds):
        a, b = start[g], start[g + 1]
        out.append(a + order_free_subset(p[a:b], cap, s) if b - a > cap else np.arange(a, b))
    return np.concatenate(out)


def covariances_numpy(p, counts):
    g = np.repeat(np.arange(len(counts)), counts)
    mean = np.stack([np.bincount(g, p[:, i]) for i in range(3)], 1) / counts[:, None]
    x = p - mean[g]
    cov = np.empty((len(counts), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(g, x[:, i] * x[:, j])
    return cov / np.maximum(counts - 1, 1)[:, None, None]


def sorted_numpy(v, g):
    lo, hi = v.min(), v.max()
    return v[np.argsort((v - lo) + g * (2.0 * (hi - lo) + 1.0), kind="stable")]


def knn_numpy(cen, m, q, n, k):
    tree = cKDTree(lifted(cen, m), balanced_tree=False, compact_nodes=False)
    return tree.query(lifted(q, n), k=k, distance_upper_bound=GAP / 2)


def nearest_numpy(p, n, cen, m):
    tree = cKDTree(lifted(p, n), balanced_tree=False, compact_nodes=False)
    return tree.query(lifted(cen, m), k=1, distance_upper_bound=GAP / 2)[0]


# --------------------------------------------------------------------- the bench

def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--pairs", type=int, default=300)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    p, n, cen, m = batch(a.pairs)
    seeds = list(range(7, 7 + a.pairs))
    seeds64 = np.array(seeds, np.uint64)
    bits = p.view(np.uint64)
    cue = subset_runs(bits, seeds64, run_starts(n), 1024, 16384)[0]
    q, nq = p[cue], np.minimum(n, 1024)
    d = np.random.default_rng(2).random(len(q))
    gq = np.repeat(np.arange(a.pairs), nq)
    run_covariances(p[:10], run_starts([10]))
    nearest_distance_runs(p[:10], run_starts([10]), cen[:3], run_starts([3]))  # compile
    cases = [
        ("seeded subsets, 1024 + 16384", f"{len(p):,} points",
         lambda: (subsets_numpy(p, n, seeds, 1024), subsets_numpy(p, n, seeds, 16384)),
         lambda: subset_runs(bits, seeds64, run_starts(n), 1024, 16384),
         lambda o, w: (p[o[0]] == p[w[0]]).all() and (p[o[1]] == p[w[1]]).all()),
        ("per-pair covariances", f"{len(p):,} points", lambda: covariances_numpy(p, n),
         lambda: run_covariances(p, run_starts(n))[1], lambda o, w: np.array_equal(o, w)),
        ("per-pair sort (percentiles)", f"{len(d):,} values", lambda: sorted_numpy(d, gq),
         lambda: sorted_segments(d, gq, a.pairs)[0], lambda o, w: np.array_equal(o, w)),
        ("8 nearest face centres", f"{len(q):,} queries", lambda: knn_numpy(cen, m, q, nq, 8),
         lambda: _pair_knn(cen, m, q, nq, 8),
         lambda o, w: np.array_equal(o[0], w[0]) and np.array_equal(o[1], w[1])),
        ("mesh -> point distance", f"{len(p):,} points", lambda: nearest_numpy(p, n, cen, m),
         lambda: nearest_distance_runs(p, run_starts(n), cen, run_starts(m)), lambda o, w: np.array_equal(o, w)),
    ]
    return run_cases(cases, a.repeat)

if __name__ == "__main__":
    main()
