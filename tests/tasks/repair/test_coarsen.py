"""Flat stretches of the fused points are coarsened before the triangulation, within an error bound;
edges, steps and noisy surfaces keep every point (tasks.repair.coarsen)."""

import numpy as np
from scipy.spatial import Delaunay

from tasks.repair.coarsen import coarsen_flat, flat_points


def _wall(step_m=0.0, noise_m=0.005, seed=0):
    """A 6 m x 3 m wall in the x-z plane at 5 cm spacing, y = depth; with a recess of ``step_m`` over
    2 < x < 4, 1 < z < 2 (a window). Returns (n, 3)."""
    x, z = np.meshgrid(np.arange(0, 6, 0.05), np.arange(0, 3, 0.05))
    x, z = x.ravel(), z.ravel()
    window = (x > 2) & (x < 4) & (z > 1) & (z < 2)
    y = np.where(window, step_m, 0.0) + np.random.default_rng(seed).normal(0, noise_m, len(x))
    return np.c_[x, y, z]


def _interpolation_error(p, keep):
    """Largest |y| difference between each dropped point and the Delaunay surface (in x-z) of the kept ones."""
    tri = Delaunay(p[keep][:, [0, 2]])
    drop = np.setdiff1d(np.arange(len(p)), keep)
    s = tri.find_simplex(p[drop][:, [0, 2]])
    assert (s >= 0).all()  # the kept points span every dropped one: the surface does not shrink
    b = np.einsum("nij,nj->ni", tri.transform[s, :2], p[drop][:, [0, 2]] - tri.transform[s, 2])
    bary = np.c_[b, 1 - b.sum(1)]
    y = np.einsum("ni,ni->n", bary, p[keep][tri.simplices[s], 1])
    return np.abs(y - p[drop, 1]).max()


def test_a_flat_noisy_wall_keeps_a_third_of_its_points_or_fewer_and_its_extent():
    p = _wall()
    keep = coarsen_flat(p, 0.15, 0.01)
    assert len(keep) < 0.35 * len(p)
    for ax in (0, 2):  # the outline stays where it was
        assert p[keep, ax].min() == p[:, ax].min() and p[keep, ax].max() == p[:, ax].max()
    assert _interpolation_error(p, keep) < 0.03  # 5 mm noise: within the noise's spread


def test_a_window_recess_keeps_its_edges_and_the_surface_stays_within_the_tolerance():
    p = _wall(step_m=0.12)
    keep = coarsen_flat(p, 0.15, 0.01)
    x, z = p[:, 0], p[:, 2]
    at_edge = ((np.abs(x - 2.025) < 0.03) | (np.abs(x - 3.975) < 0.03)) & (z > 1.1) & (z < 1.9)
    assert np.isin(np.flatnonzero(at_edge), keep).all()  # the last point on either side of the step stays
    assert _interpolation_error(p, keep) < 0.03
    # without the rule (every other point dropped blindly) the step's error shows: the check can fail
    blind = np.arange(0, len(p), 3)
    outline = np.flatnonzero((x == 0) | (z == 0) | (x > 5.94) | (z > 2.94))
    assert _interpolation_error(p, np.union1d(blind, outline)) > 0.05


def test_a_rough_surface_keeps_its_points():
    p = _wall(noise_m=0.03)  # ~14 neighbours per point: a rare one fits the plane by chance
    assert flat_points(p, 0.15, 0.01).mean() < 0.002
    assert len(coarsen_flat(p, 0.15, 0.01)) > 0.998 * len(p)
    assert flat_points(_wall(noise_m=0.004), 0.15, 0.01).mean() > 0.8  # the same wall, smooth: mostly flat


def test_off_and_tiny_inputs_keep_everything():
    p = _wall()
    assert (coarsen_flat(p, 0.0, 0.01) == np.arange(len(p))).all()
    assert (coarsen_flat(p[:5], 0.15, 0.01) == np.arange(5)).all()
    assert len(coarsen_flat(np.zeros((0, 3)), 0.15, 0.01)) == 0


def test_far_from_the_origin_the_decision_is_the_same():
    p = _wall(step_m=0.12)
    far = p + np.array([5.0e5, 5.4e6, 300.0])  # projected coordinates, not shifted
    near_f, far_f = flat_points(p, 0.15, 0.01), flat_points(far, 0.15, 0.01)
    assert near_f.mean() > 0.5 and np.mean(near_f == far_f) > 0.99  # voxel edges may round either way


def _wall_region():
    """A 16 m x 6 m wall mesh at 0.5 m, its 10 m x 3 m middle to rebuild; MLS points every 2 cm on the true wall 10 cm
    behind it (4 mm noise). Returns (RegionInput, the MLS points (p, 3))."""
    from tasks.repair.region_geometry import RegionInput

    xs, zs = np.linspace(0, 16, 33), np.linspace(0, 6, 13)  # a 16 m x 6 m wall at 0.5 m
    v = np.array([[x, 0.0, z] for x in xs for z in zs])
    f = []
    for i in range(32):
        for j in range(12):
            a, b = i * 13 + j, (i + 1) * 13 + j
            f += [[a, b, b + 1], [a, b + 1, a + 1]]
    f = np.array(f, np.int64)
    c = v[f].mean(axis=1)
    zone = (c[:, 0] > 3) & (c[:, 0] < 13) & (c[:, 2] > 1.5) & (c[:, 2] < 4.5)  # a 10 m x 3 m zone, context around
    rng = np.random.default_rng(1)
    seen = np.array([[x, 0.1, z] for x in np.arange(0.01, 16, 0.02) for z in np.arange(0.01, 6, 0.02)])
    seen[:, 1] += rng.normal(0, 0.004, len(seen))  # the wall is 10 cm behind the mesh, 4 mm noise
    in_zone = (seen[:, 0] > 3) & (seen[:, 0] < 13) & (seen[:, 2] > 1.5) & (seen[:, 2] < 4.5)
    near = (v[:, 0] > 2.4) & (v[:, 0] < 13.6) & (v[:, 2] > 0.9) & (v[:, 2] < 5.1)
    data = RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=f[zone], context_faces=f[~zone],
                       near_zone=near, mls_xyz=seen[in_zone], mls_class=np.zeros(int(in_zone.sum()), np.uint8),
                       ctx_xyz=seen[~in_zone][::4], face_normals=None)
    return data, seen


def test_a_region_rebuilds_with_fewer_faces_and_the_same_surface():
    from tasks.config.repair import RepairConfig
    from tasks.repair.region_geometry import repair_region_geometry

    data, seen = _wall_region()
    full = repair_region_geometry(data, RepairConfig.model_validate({"mesh": {"flat_spacing_m": 0}}))
    coarse = repair_region_geometry(data, RepairConfig.model_validate({}))
    assert coarse.stats["flat_dropped"] > 0 and "flat_dropped" not in full.stats
    assert coarse.mesh.n_faces < 0.5 * full.mesh.n_faces
    assert (coarse.replaced == full.replaced).all()
    from tasks.repair.mesh import ClosestPoint

    inner_pts = seen[(seen[:, 0] > 3.6) & (seen[:, 0] < 12.4) & (seen[:, 2] > 2.1) & (seen[:, 2] < 3.9)]
    for geo in (full, coarse):
        c = geo.mesh.xyz[geo.mesh.faces].mean(axis=1)
        inner = (c[:, 0] > 3.6) & (c[:, 0] < 12.4) & (c[:, 2] > 2.1) & (c[:, 2] < 3.9)
        assert np.mean(np.abs(c[inner, 1] - 0.1) < 0.02) > 0.99  # on the scanned wall
        fid, _, dist = ClosestPoint(geo.mesh.xyz, geo.mesh.faces).query(inner_pts)
        assert (fid >= 0).all() and np.quantile(dist, 0.99) < 0.015  # and covering it: no hole, no shrink
    assert coarse.stats["rebuilt_area_m2"] <= full.stats["rebuilt_area_m2"]  # no surface added


def test_without_thinning_every_point_is_fused_and_the_wall_is_the_same():
    from tasks.config.repair import RepairConfig
    from tasks.repair.region_geometry import repair_region_geometry

    data, _ = _wall_region()
    cfg = {"mesh": {"flat_spacing_m": 0}}
    thinned = repair_region_geometry(data, RepairConfig.model_validate(cfg))
    every = repair_region_geometry(data, RepairConfig.model_validate({**cfg, "fusion": {"thin": False}}))
    assert every.stats["mls_thinned"] == every.stats["mls_points"] == len(data.mls_xyz)
    assert thinned.stats["mls_thinned"] < 0.5 * len(data.mls_xyz)  # 2 cm points, 5 cm voxels
    assert every.stats["plan"] == thinned.stats["plan"] and (every.replaced == thinned.replaced).all()
    for geo in (thinned, every):
        c = geo.mesh.xyz[geo.mesh.faces].mean(axis=1)
        inner = (c[:, 0] > 3.6) & (c[:, 0] < 12.4) & (c[:, 2] > 2.1) & (c[:, 2] < 3.9)
        assert np.mean(np.abs(c[inner, 1] - 0.1) < 0.02) > 0.99
    assert every.mesh.n_faces > 3 * thinned.mesh.n_faces


def _framed_wall(seed=0):
    """A 4 m x 3 m wall (x-z plane, y = depth) scanned every 1 cm with 3 mm noise, with a window frame: a bar
    8 cm wide standing 10 cm proud of the wall (y = -0.1) around a 1 m x 1 m opening at 1.5 < x < 2.5,
    1 < z < 2, its glass 15 cm behind (y = 0.15). Returns ((n, 3) points, (n,) bool on the frame)."""
    x, z = np.meshgrid(np.arange(0, 4, 0.01), np.arange(0, 3, 0.01))
    x, z = x.ravel(), z.ravel()
    outer = (x > 1.42) & (x < 2.58) & (z > 0.92) & (z < 2.08)
    glass = (x > 1.5) & (x < 2.5) & (z > 1) & (z < 2)
    frame = outer & ~glass
    y = np.where(frame, -0.1, np.where(glass, 0.15, 0.0)) + np.random.default_rng(seed).normal(0, 0.003, len(x))
    return np.c_[x, y, z], frame


def test_detail_thinning_keeps_the_fine_points_only_where_the_surface_is_not_flat():
    from tasks.config.repair import RepairConfig
    from tasks.repair.coarsen import thin_with_detail
    from tasks.repair.fuse import thin_points

    fc = RepairConfig().fusion
    p, frame = _framed_wall()
    plain = thin_points(p, 0.05)
    keep = thin_with_detail(p, 0.05, fc.detail_spacing_m, fc.detail_radius_m, fc.detail_tolerance_m)  # as the repair calls it
    assert (np.diff(keep) > 0).all()
    inside = (p[:, 0] > 0.3) & (p[:, 0] < 3.7) & (p[:, 2] > 0.3) & (p[:, 2] < 2.7)  # the scan's edge is no plane
    far = inside & ((np.abs(p[:, 0] - 2) > 0.9) | (np.abs(p[:, 2] - 1.5) > 0.9))  # wall well clear of the frame
    # the flat wall keeps its 5 cm points exactly; the frame gets ~twice as many (2.5 cm voxels)
    assert set(keep[far[keep]].tolist()) == set(plain[far[plain]].tolist())
    assert frame[keep].sum() > 1.6 * frame[plain].sum()
    assert len(keep) < 1.3 * len(plain)
    # off, or a detail voxel no finer than the spacing: the plain thinning
    assert (thin_with_detail(p, 0.05, 0.0, 0.15, 0.015) == plain).all()
    assert (thin_with_detail(p, 0.05, 0.05, 0.15, 0.015) == plain).all()


def test_the_hole_area_does_not_grow_with_the_points_density():
    from types import SimpleNamespace

    from tasks.repair.region_geometry import _hole_area_m2

    x, z = np.meshgrid(np.arange(0, 1, 0.025), np.arange(0, 1, 0.025))  # 1 m² of scanned wall at 2.5 cm
    mls = np.c_[x.ravel(), np.zeros(x.size), z.ravel()]
    mesh = np.array([[10.0, 0, 0], [11, 0, 0], [10, 0, 1]])  # the mesh is 9 m away: all of it is hole
    data = SimpleNamespace(xyz=mesh)
    n = np.tile([0.0, 1, 0], (len(mls), 1))
    fine = _hole_area_m2(data, np.arange(3), mls, n, 0.05)
    coarse = _hole_area_m2(data, np.arange(3), mls[::4], n[::4], 0.05)
    assert 0.9 <= fine <= 1.1 and abs(fine - 1.0) <= abs(coarse - 1.0) + 0.05
