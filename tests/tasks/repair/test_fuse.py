"""Graph-cut fusion (§5.1) on hand-made planes."""

import numpy as np

from tasks.repair.fuse import FusionParams, graph_cut_fuse, pca_normals, thin_points


def _planes():
    """Mesh vertices on z = 0.1 over [0, 4] x [0, 2] (0.2 m grid); accurate MLS on z = 0 over [0, 2] x [0, 2]."""
    gx, gy = np.meshgrid(np.arange(0, 4.01, 0.2), np.arange(0, 2.01, 0.2), indexing="ij")
    mesh = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 0.1)]
    px, py = np.meshgrid(np.arange(0, 2.001, 0.04), np.arange(0, 2.001, 0.04), indexing="ij")
    rng = np.random.default_rng(0)
    mls = np.c_[px.ravel(), py.ravel(), rng.normal(0, 0.003, px.size)]
    up = lambda n: np.tile([0.0, 0.0, 1.0], (n, 1))
    return mesh, up(len(mesh)), mls, up(len(mls))


def test_exactly_the_covered_vertices_are_replaced():
    mesh, mn, mls, pn = _planes()
    r = graph_cut_fuse(mesh, mn, mls, pn, FusionParams(sigma_distance_m=0.08))
    covered = mesh[:, 0] <= 2.0 + 1e-9
    assert covered.sum() == 121 and (~covered).sum() == 110
    np.testing.assert_array_equal(r.replaced, covered)
    assert r.accepted.all()  # the accurate points all join the fused set
    assert abs(r.energy - r.flow) < 1e-6 * max(1.0, r.flow)  # a real min-cut: its value is the energy
    fused, src = r.fused(mesh, mls)
    assert (src == 0).sum() == 110 and np.all(fused[src == 0][:, 0] > 2.0)


def test_points_far_in_front_of_the_mesh_are_rejected():
    mesh, mn, mls, pn = _planes()
    fence = mls[:200] + [0.0, 0.0, 1.5]  # 1.5 m in front of the surface, beyond point_reach_m
    r = graph_cut_fuse(mesh, mn, np.concatenate([mls, fence]), np.concatenate([pn, pn[:200]]), FusionParams())
    assert not r.accepted[-200:].any() and r.accepted[:-200].all()


def test_forced_and_locked_vertices():
    mesh, mn, mls, pn = _planes()
    forced = mesh[:, 0] > 3.5
    locked = mesh[:, 0] < 0.3
    r = graph_cut_fuse(mesh, mn, mls, pn, FusionParams(sigma_distance_m=0.08), forced=forced, locked=locked)
    assert r.replaced[forced].all() and not r.replaced[locked].any()


def test_pca_normals_and_thinning():
    rng = np.random.default_rng(1)
    xyz = np.c_[rng.uniform(0, 1, (2000, 2)), np.zeros(2000)]
    n, var = pca_normals(xyz, 10)
    assert np.allclose(np.abs(n[:, 2]), 1.0, atol=1e-6) and var.max() < 1e-9
    keep = thin_points(xyz, 0.1)
    assert len(keep) == len(np.unique(np.floor(xyz[keep] / 0.1).astype(int), axis=0)) <= 100
