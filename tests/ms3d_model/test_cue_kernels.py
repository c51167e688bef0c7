"""The classify cues' compiled per-pair loops against the numpy code they replaced (built here): the
batched subset equals ``order_free_subset`` pair by pair, the covariances equal the ``np.bincount`` sums."""

import numpy as np

from ms3d_model.cue_kernels import run_covariances, run_starts, subset_runs
from ms3d_model.hashing import order_free_subset


def _runs(rng, sizes):
    pts = [rng.normal(scale=5.0, size=(n, 3)) for n in sizes]
    return pts, np.concatenate(pts), np.array(sizes, np.int64)


def test_subset_runs_equals_order_free_subset_of_every_pair_at_both_sizes():
    rng = np.random.default_rng(4)
    pts, p_all, counts = _runs(rng, [5, 3000, 1024, 1025, 40000, 1, 2500, 3001])
    pts[1][100:140] = pts[1][7]  # identical points: interchangeable rows, the same coordinates picked
    p_all = np.concatenate(pts)
    seeds = [11, 2**63 + 5, 0, 3, 77, 9, 2**64 - 1, 5]
    start = run_starts(counts)
    small, large = subset_runs(p_all.view(np.uint64), np.array(seeds, np.uint64), start, 1024, 3000)
    for rows, cap in ((small, 1024), (large, 3000)):
        ref = np.concatenate([p[order_free_subset(p, cap, s)] if len(p) > cap else p for p, s in zip(pts, seeds)])
        assert len(rows) == sum(min(len(p), cap) for p in pts)
        np.testing.assert_array_equal(p_all[rows], ref)
    # a pair's subset does not depend on its rows' order, nor on the other pairs
    perm = rng.permutation(40000)
    alone, _ = subset_runs(pts[4][perm].view(np.uint64), np.array([77], np.uint64), run_starts([40000]), 1024, 3000)
    np.testing.assert_array_equal(pts[4][perm][alone], pts[4][order_free_subset(pts[4], 1024, 77)])


def test_run_covariances_equal_the_bincount_sums():
    rng = np.random.default_rng(5)
    _, p, counts = _runs(rng, [1, 2, 3, 500, 17])
    g = np.repeat(np.arange(len(counts)), counts)
    mean = np.stack([np.bincount(g, p[:, i]) for i in range(3)], 1) / counts[:, None]
    x = p - mean[g]
    cov = np.empty((len(counts), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(g, x[:, i] * x[:, j])
    cov /= np.maximum(counts - 1, 1)[:, None, None]
    m, c = run_covariances(p, run_starts(counts))
    np.testing.assert_array_equal(m, mean)
    np.testing.assert_array_equal(c, cov)
    assert c[0].max() == 0.0 and c[3].trace() > 10.0  # one point: no spread; 500 normal points: ~75


def test_nearest_distance_runs_equals_a_kd_tree_per_run_on_awkward_point_sets():
    from scipy.spatial import cKDTree

    from ms3d_model.grid_search import nearest_distance_runs

    rng = np.random.default_rng(6)
    P, Q = [], []
    for kind in range(5):
        n = 3000
        p = [np.c_[rng.uniform(0, 5, (n, 2)), 0.01 * rng.normal(size=n)],  # a noisy plane
             np.c_[rng.uniform(0, 5, n), np.zeros(n), np.zeros(n)],  # a line
             np.repeat(rng.normal(size=(1, 3)), n, 0),  # one point, repeated
             rng.normal(size=(n, 3)) * [10, 0.1, 3],  # a thin blob
             rng.normal(size=(1, 3))][kind] + rng.uniform(0, 100, 3)  # a single point
        q = p[rng.integers(0, len(p), 200)] + rng.normal(scale=[0.3, 0.3, 2.0], size=(200, 3))
        q[:5] += 40.0  # far from every point: past the ring search
        q[5:10] = p[:5]  # on a point: distance 0
        P.append(p)
        Q.append(q)
    P.append(np.zeros((0, 3)))  # a run without points: inf
    Q.append(rng.normal(size=(3, 3)))
    got = nearest_distance_runs(np.concatenate(P), run_starts([len(p) for p in P]), np.concatenate(Q),
                                run_starts([len(q) for q in Q]))
    ref = np.concatenate([cKDTree(p).query(q)[0] for p, q in zip(P[:-1], Q[:-1])] + [np.full(3, np.inf)])
    np.testing.assert_array_equal(got, ref)
    assert (got[5:10] == 0).all() and got[:5].min() > 30
