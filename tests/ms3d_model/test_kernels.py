"""The compiled kernels against plain numpy references built here (each would fail on a wrong sign,
index or region of the triangle)."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ms3d_model.kernels import closest_points_on_triangles, eig3, knn_pca, local_planes, nearest_to_centroid


def _sym(rng, n):
    a = rng.normal(size=(n, 3, 3))
    return a + a.transpose(0, 2, 1)


def test_eig3_matches_lapack_including_repeated_and_tiny_eigenvalues():
    rng = np.random.default_rng(3)
    mats = list(_sym(rng, 200))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    mats += [q @ np.diag([1e-9, 1.0, 1.0]) @ q.T, q @ np.diag([2.0, 2.0, 2.0]) @ q.T, np.zeros((3, 3)),
             np.diag([3.0, 1.0, 2.0])]
    w, v = np.empty(3), np.empty((3, 3))
    for m in mats:
        eig3(m.copy(), w, v)
        ref = np.linalg.eigvalsh(m)
        np.testing.assert_allclose(w, ref, atol=1e-12 * max(1.0, np.abs(ref).max()))
        np.testing.assert_allclose(v.T @ v, np.eye(3), atol=1e-12)
        np.testing.assert_allclose(m @ v, v * w, atol=1e-11 * max(1.0, np.abs(ref).max()))
    eig3(np.diag([1e-9, 1.0, 1.0]) @ np.eye(3), w, v)  # a plane's covariance: its normal is the smallest
    assert abs(v[0, 0]) == pytest.approx(1.0)


def test_knn_pca_equals_the_numpy_pca():
    rng = np.random.default_rng(0)
    xyz = np.c_[rng.uniform(0, 2, (3000, 2)), rng.normal(scale=0.01, size=3000)]
    xyz[:1000, 2] += xyz[:1000, 0]  # a slope beside the flat part
    _, idx = cKDTree(xyz).query(xyz, k=10)
    nb = xyz[idx] - xyz[idx].mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb) / 10)
    n, var = knn_pca(xyz, idx.astype(np.int64))
    np.testing.assert_allclose(np.abs((n * v[:, :, 0]).sum(1)), 1.0, atol=1e-9)
    np.testing.assert_allclose(var, w[:, 0] / w.sum(1), atol=1e-12)


def _closest_reference(p, tri, samples=400):
    """Brute force: the nearest of a dense barycentric sampling of the triangle (and its three edges)."""
    s = np.linspace(0, 1, samples)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1
    bary = np.c_[u[keep], v[keep]]
    pts = tri[0] + bary[:, :1] * (tri[1] - tri[0]) + bary[:, 1:] * (tri[2] - tri[0])
    return pts[np.argmin(((pts - p) ** 2).sum(1))]


def test_closest_points_on_triangles_in_every_region_and_on_degenerate_faces():
    rng = np.random.default_rng(5)
    tri = np.array([[[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]])
    # one query in each of Ericson's seven regions, off the plane
    p = np.array([[-1, -1, .3], [2, -.5, .3], [-.5, 2, .3], [.5, -1, .3], [-1, .5, .3], [1, 1, .3], [.2, .2, .3]])
    got = closest_points_on_triangles(p, tri, np.zeros(len(p), np.int64))
    want = [[0, 0, 0], [1, 0, 0], [0, 1, 0], [.5, 0, 0], [0, .5, 0], [.5, .5, 0], [.2, .2, 0]]
    np.testing.assert_allclose(got, want, atol=1e-12)
    tris = rng.normal(size=(20, 3, 3))
    q = rng.normal(size=(20, 3)) * 2
    got = closest_points_on_triangles(q, tris, np.arange(20, dtype=np.int64))
    for i in range(20):
        ref = _closest_reference(q[i], tris[i])
        assert np.linalg.norm(got[i] - q[i]) <= np.linalg.norm(ref - q[i]) + 1e-9
        assert np.linalg.norm(got[i] - ref) < 0.05
    seg = np.array([[[0.0, 0, 0], [2, 0, 0], [1, 0, 0]]])  # collinear: the longest side, 0 -> 2
    np.testing.assert_allclose(closest_points_on_triangles(np.array([[1.5, 1, 0], [3, 0, 0]]), seg,
                                                           np.zeros(2, np.int64)), [[1.5, 0, 0], [2, 0, 0]])


def test_nearest_to_centroid_picks_the_first_row_of_a_tie():
    xyz = np.array([[0.0, 0, 0], [2, 0, 0], [1, 0, 0], [5, 0, 0], [4, 0, 0], [6, 0, 0], [9, 0, 0]])
    order = np.array([0, 1, 2, 3, 4, 5, 6], np.int64)  # groups {0, 1, 2}, {3, 4, 5}, {6}
    np.testing.assert_array_equal(nearest_to_centroid(xyz, order, np.array([0, 3, 6], np.int64)), [2, 3, 6])
    tie = np.array([[0.0, 0, 0], [2, 0, 0]])
    np.testing.assert_array_equal(nearest_to_centroid(tie, np.array([0, 1], np.int64), np.array([0], np.int64)), [0])


def _planes_reference(q, ref, j, d, tol, max_gap):
    ok = np.isfinite(d)
    cnt = np.maximum(ok.sum(1), 1)
    rel = ref[np.where(ok, j, 0)] - q[:, None]
    mean = (rel * ok[..., None]).sum(1) / cnt[:, None]
    nb = (rel - mean[:, None]) * ok[..., None]
    lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb) / cnt[:, None, None])
    planar = np.sqrt(np.maximum(lam[:, 0], 0)) <= tol
    gaps = []
    for i in range(len(q)):
        use = ok[i] & (d[i] > 1e-9)
        a = np.sort(np.arctan2(rel[i, use] @ vec[i, :, 1], rel[i, use] @ vec[i, :, 2]))
        gaps.append(2 * np.pi if len(a) < 2 else max(np.diff(a).max(initial=0), a[0] + 2 * np.pi - a[-1]))
    return (ok.sum(1) >= 6) & planar & (np.array(gaps) <= max_gap)


def test_local_planes_equals_the_plane_and_edge_test_written_in_numpy():
    rng = np.random.default_rng(2)
    g = np.stack(np.meshgrid(np.arange(30), np.arange(30)), -1).reshape(-1, 2) * 0.05
    xyz = np.c_[g, np.where(g[:, 0] > 0.8, 0.08, 0.0) + rng.normal(scale=0.003, size=len(g))]  # a step
    d, j = cKDTree(xyz).query(xyz, k=24, distance_upper_bound=0.15)
    got = local_planes(xyz, xyz, j.astype(np.int64), d, 0.01, True, np.radians(120))
    want = _planes_reference(xyz, xyz, j, d, 0.01, np.radians(120))
    assert 0.2 < want.mean() < 0.9  # flat middles pass, the step, the edges and the corners do not
    np.testing.assert_array_equal(got, want)
    no_edges = local_planes(xyz, xyz, j.astype(np.int64), d, 0.01, False, np.radians(120))
    assert no_edges.sum() > got.sum() and not (got & ~no_edges).any()


def test_nearest_of_candidates_equals_the_nearest_of_every_candidate_face():
    from ms3d_model.kernels import nearest_of_candidates

    rng = np.random.default_rng(8)
    tri = rng.normal(size=(40, 3, 3))
    tri[0] = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    p = np.r_[rng.normal(size=(300, 3)) * 2, [[0.2, 0.2, 0.0]]]  # the last one lies on face 0
    centres = tri.mean(axis=1)
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = cross / np.linalg.norm(cross, axis=1, keepdims=True)
    radius = np.linalg.norm(tri - centres[:, None], axis=2).max(axis=1)
    dc = np.linalg.norm(p[:, None] - centres[None], axis=2)
    cand = np.argsort(dc, axis=1, kind="stable")
    cand_d = np.take_along_axis(dc, cand, axis=1)
    cand, cand_d = np.c_[cand, np.full(len(p), len(tri))], np.c_[cand_d, np.full(len(p), np.inf)]  # a "none"
    d, signed, off = nearest_of_candidates(p, tri, normals, radius, cand.astype(np.int64), cand_d)
    every = np.stack([np.linalg.norm(closest_points_on_triangles(p, tri, np.full(len(p), f, np.int64)) - p, axis=1)
                      for f in range(len(tri))], axis=1)
    np.testing.assert_allclose(d, every.min(axis=1), rtol=0, atol=1e-12)
    best = every.argmin(axis=1)
    foot = closest_points_on_triangles(p, tri, best.astype(np.int64))
    want = np.sign(((p - foot) * normals[best]).sum(1)) * every.min(axis=1)
    np.testing.assert_allclose(signed, want, atol=1e-12)
    assert signed[-1] == 0.0 and (signed[:-1] != 0).all() and (signed < 0).any() and (signed > 0).any()
    np.testing.assert_allclose(off, ((p - foot) * normals[best]).sum(1), atol=1e-12)
    assert (np.abs(off) <= d + 1e-12).all() and (np.sign(off) == np.sign(signed)).all()
