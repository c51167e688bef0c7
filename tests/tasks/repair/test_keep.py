"""Overhead faces (tasks.repair.keep): a street scanner sees a horizontal surface above its head from below
only, so the soffit under an eave is not evidence of the roof's top above it."""

import numpy as np

from tasks.config.repair import RepairConfig
from tasks.repair.keep import covered_along_normal, overhead_faces, top_faces, unseen_faces


def _grid(x0, x1, y0, y1, z, n=8):
    """A horizontal quad grid at height z: (vertices (k, 3), faces (m, 3) int64), up-facing."""
    xs, ys = np.linspace(x0, x1, n + 1), np.linspace(y0, y1, n + 1)
    v = np.array([[x, y, z] for x in xs for y in ys])
    idx = lambda i, j: i * (n + 1) + j
    f = [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)] for i in range(n) for j in range(n)]
    f += [[idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)] for i in range(n) for j in range(n)]
    return v, np.array(f, np.int64)


def _plane_points(x0, x1, y0, y1, z, step=0.05):
    g = np.stack(np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step)), -1).reshape(-1, 2)
    return np.c_[g, np.full(len(g), z)]


def test_points_under_an_overhead_face_are_not_evidence_of_it_but_points_on_or_above_are():
    v, f = _grid(0, 2, 0, 2, 6.0)
    wall = np.c_[np.full(200, -3.0), np.linspace(0, 2, 200), np.linspace(0, 5, 200)]  # the region's low points
    soffit = _plane_points(0, 2, 0, 2, 5.75)  # 25 cm under the face
    oh = overhead_faces(v, f, np.concatenate([wall, soffit]), min_height_m=2.5)
    assert oh.all()
    no_cover = np.zeros(len(v), bool)
    kw = {"clear_m": 0.5, "step_m": 0.4}
    assert unseen_faces(v, f, np.concatenate([wall, soffit]), no_cover, overhead=oh, **kw).all()
    assert not unseen_faces(v, f, np.concatenate([wall, soffit]), no_cover, **kw).any()  # the old rule: all seen
    on_top = _plane_points(0, 2, 0, 2, 6.02)  # points on the face (within the 5 cm tolerance) do count
    assert not unseen_faces(v, f, np.concatenate([wall, soffit, on_top]), no_cover, overhead=oh, **kw).any()
    above = _plane_points(0, 2, 0, 2, 6.3)
    assert not unseen_faces(v, f, np.concatenate([wall, above]), no_cover, overhead=oh, **kw).any()
    fascia = np.array([[x, -0.3, z] for x in np.arange(0, 2, 0.05) for z in np.arange(5.7, 6.15, 0.05)])
    edge = (v[f][:, :, 1] < 0.3).all(axis=1)  # the strip within clear_m of the fascia, 10 cm over it at most
    assert not unseen_faces(v, f, np.concatenate([wall, fascia]), no_cover, **kw)[edge].any()
    pts = np.concatenate([wall, fascia])
    along_y = np.tile([0, 1.0, 0], (len(pts), 1))
    assert unseen_faces(v, f, pts, no_cover, overhead=oh, mls_n=along_y, **kw).all()  # beside, facing sideways
    assert not unseen_faces(v, f, pts, no_cover, overhead=oh, **kw)[edge].any()  # without normals: counted
    up = np.tile([0, 0, 1.0], (len(pts), 1))
    assert not unseen_faces(v, f, pts, no_cover, overhead=oh, mls_n=up, **kw)[edge].any()  # a roof-like surface


def test_a_roofs_top_takes_evidence_only_from_points_above_it():
    """An overhead face wound upward is a top: a scanner below never saw it, so points on its plane (a thin
    slab's soffit, 3 cm under a sagging mesh roof) are no evidence; with the winding unknown they are."""
    v, f = _grid(0, 2, 0, 2, 6.0)
    assert top_faces(v, f).all() and not top_faces(v, f[:, ::-1]).any()
    low = np.c_[np.full(200, -3.0), np.linspace(0, 2, 200), np.linspace(0, 5, 200)]
    thin = _plane_points(0, 2, 0, 2, 5.97)
    pts = np.concatenate([low, thin])
    oh = overhead_faces(v, f, pts, min_height_m=2.5)
    kw = {"clear_m": 0.5, "step_m": 0.4, "overhead": oh, "mls_n": np.tile([0, 0, 1.0], (len(pts), 1))}
    no_cover = np.zeros(len(v), bool)
    assert not unseen_faces(v, f, pts, no_cover, **kw).any()
    assert unseen_faces(v, f, pts, no_cover, top=top_faces(v, f), **kw).all()
    above = np.concatenate([low, _plane_points(0, 2, 0, 2, 6.3)])  # something over the roof does count
    assert not unseen_faces(v, f, above, no_cover, top=top_faces(v, f),
                            **{**kw, "mls_n": np.tile([0, 0, 1.0], (len(above), 1))}).any()


def test_a_low_horizontal_face_is_not_overhead_and_the_ground_under_it_still_counts():
    """A ground mesh floating 25 cm over the scanned ground is seen (the scanner looks down on it)."""
    v, f = _grid(0, 2, 0, 2, 0.25)
    ground = _plane_points(-1, 3, -1, 3, 0.0)
    assert not overhead_faces(v, f, ground, min_height_m=2.5).any()
    vn = np.tile([0, 0, 1.0], (len(v), 1))
    cov = covered_along_normal(v, vn, ground, vn[:1].repeat(len(ground), 0), depth_m=1.2, lateral_m=0.075)
    assert cov.all()
    assert not unseen_faces(v, f, ground, cov, clear_m=0.5, step_m=0.4).any()
    steep = v.copy()
    steep[:, 2] += 6.0 + 2.0 * steep[:, 0]  # 63° from horizontal, high up: a wall-like face is never overhead
    assert not overhead_faces(steep, f, ground, min_height_m=2.5).any()


def test_covered_along_normal_ignores_a_soffit_under_an_overhead_vertex():
    v, _ = _grid(0, 2, 0, 2, 6.0)
    soffit = _plane_points(0, 2, 0, 2, 5.75)
    vn = np.tile([0, 0, 1.0], (len(v), 1))
    sn = vn[:1].repeat(len(soffit), 0)
    kw = {"depth_m": 1.2, "lateral_m": 0.075}
    assert covered_along_normal(v, vn, soffit, sn, **kw).all()
    assert not covered_along_normal(v, vn, soffit, sn, overhead=np.ones(len(v), bool), **kw).any()


def _eave_region():
    """A wall (x-z plane at y = 0, z 0..6, street at y < 0) under a flat roof at z = 6 that overhangs the
    street by 0.6 m; the MLS sees the wall (15 cm off the mesh: a misregistered storey) and the eave's
    soffit 25 cm under the roof's top, never the top. Returns (RegionInput, (m,) bool overhang roof faces)."""
    from tasks.repair.region_geometry import RegionInput

    xs, zs = np.linspace(0, 8, 33), np.linspace(0, 6, 25)
    wv = np.array([[x, 0.0, z] for x in xs for z in zs])
    idx = lambda i, j: i * len(zs) + j
    wf = [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)] for i in range(32) for j in range(24)]
    wf += [[idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)] for i in range(32) for j in range(24)]
    rv, rf = _grid(0, 8, -0.6, 2.0, 6.0, n=32)
    v, f = np.concatenate([wv, rv]), np.concatenate([np.array(wf, np.int64), rf + len(wv)])
    rng = np.random.default_rng(3)
    wall = np.c_[rng.uniform(0, 8, 20000), rng.normal(-0.15, 0.004, 20000), rng.uniform(0.0, 5.7, 20000)]
    soffit = np.c_[rng.uniform(0, 8, 6000), rng.uniform(-0.6, -0.15, 6000), rng.normal(5.75, 0.004, 6000)]
    mls = np.concatenate([wall, soffit])
    data = RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=f, context_faces=np.zeros((0, 3), np.int64),
                       near_zone=np.ones(len(v), bool), mls_xyz=mls, mls_class=np.zeros(len(mls), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=None)
    c = v[f].mean(axis=1)
    return data, (np.arange(len(f)) >= len(wf)) & (c[:, 1] < -0.05)


def test_the_roof_over_an_eave_stays_while_the_wall_under_it_is_rebuilt():
    """The default keeps every roof face over the overhang and rebuilds the wall onto its scan; with the
    rule off (overhead_min_height_m 0, the code before it) the soffit takes the roof's faces."""
    from tasks.repair.region_geometry import repair_region_geometry

    data, overhang = _eave_region()
    base = {"mesh": {"max_hole_loop_m": 5.0}}
    geo = repair_region_geometry(data, RepairConfig.model_validate(base))
    assert not geo.replaced[overhang].any()
    c = data.xyz[data.zone_faces].mean(axis=1)
    wall = np.abs(data.xyz[data.zone_faces][:, :, 1]).max(axis=1) < 1e-9
    assert geo.replaced[wall & (c[:, 2] > 0.5) & (c[:, 2] < 5.0)].all()
    m = geo.mesh
    mc = m.xyz[m.faces].mean(axis=1)
    mid = (mc[:, 2] > 0.5) & (mc[:, 2] < 5.0) & (mc[:, 0] > 0.5) & (mc[:, 0] < 7.5)
    assert mid.sum() > 50 and np.median(np.abs(mc[mid, 1] + 0.15)) < 0.02  # the wall moved onto the scan
    assert not ((mc[:, 1] < -0.2) & (mc[:, 2] > 5.9)).any()  # nothing rebuilt on the kept roof's top (the soffit may be)
    off = repair_region_geometry(data, RepairConfig.model_validate({"mesh": {"max_hole_loop_m": 5.0,
                                                                             "overhead_min_height_m": 0}}))
    assert off.replaced[overhang].mean() > 0.5


def test_a_roof_seen_only_through_its_soffit_is_kept_whole_and_says_so():
    """A region whose zone is the overhanging roof alone: every face is kept (the soffit is no evidence of
    it), nothing is replaced, and the region's plan says the input mesh was kept, not re-triangulated."""
    from tasks.repair.region_geometry import RegionInput, repair_region_geometry

    v, f = _grid(0, 8, -0.6, 2.0, 6.0, n=32)
    rng = np.random.default_rng(5)
    soffit = np.c_[rng.uniform(0, 8, 6000), rng.uniform(-0.6, -0.15, 6000), rng.normal(5.75, 0.004, 6000)]
    ground = np.c_[rng.uniform(0, 8, 6000), rng.uniform(-6, -1, 6000), rng.normal(0.0, 0.004, 6000)]
    mls = np.concatenate([soffit, ground])
    data = RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=f, context_faces=np.zeros((0, 3), np.int64),
                       near_zone=np.ones(len(v), bool), mls_xyz=mls, mls_class=np.zeros(len(mls), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=None)
    geo = repair_region_geometry(data, RepairConfig())
    assert geo.stats["kept_unseen_faces"] == len(f) and not geo.replaced.any()
    assert geo.stats["plan"].startswith("unseen by the MLS") and "re-triangulated" not in geo.stats["plan"]
    off = repair_region_geometry(data, RepairConfig.model_validate({"mesh": {"overhead_min_height_m": 0}}))
    assert off.replaced.any()  # without the rule the soffit takes the roof: the test can fail


def test_tidy_keep_removes_specks_both_ways():
    """A kept roof with a scatter of single faces to rebuild (near a railing's points) becomes one kept piece;
    a single kept face inside a big piece to rebuild is rebuilt; a big piece to rebuild stays one."""
    from tasks.repair.chart import face_components
    from tasks.repair.keep import tidy_keep

    v, f = _grid(0, 8, 0, 8, 6.0, n=32)  # 0.25 m cells: 2,048 faces of 0.03 m²
    rng = np.random.default_rng(0)
    keep = np.ones(len(f), bool)
    keep[rng.choice(len(f), 60, replace=False)] = False
    assert len(np.unique(face_components(f[~keep], len(v)))) > 40
    assert tidy_keep(v, f, keep, np.ones(len(f), bool), 1.0).all()
    assert not tidy_keep(v, f, keep, np.ones(len(f), bool), 0.0).all()  # off: as found
    half = v[f].mean(axis=1)[:, 0] < 4.0
    keep = half.copy()
    keep[np.flatnonzero(~half)[100]] = True  # a speck kept inside the half to rebuild
    out = tidy_keep(v, f, keep, np.zeros(len(f), bool), 1.0)
    assert (out == half).all()


def _profile_mesh(profile: np.ndarray, outward: np.ndarray, xs: np.ndarray):
    """A y-z polyline profile (p, 2) extruded along x: (vertices, faces (m, 3) int64), each segment's faces
    wound so their normals point along its outward direction (p - 1, 3)."""
    p = len(profile)
    v = np.array([[x, y, z] for x in xs for y, z in profile])
    f = []
    for i in range(len(xs) - 1):
        for j in range(p - 1):
            a, b, c, d = i * p + j, (i + 1) * p + j, (i + 1) * p + j + 1, i * p + j + 1
            for t in ([a, b, c], [a, c, d]):
                n = np.cross(v[t[1]] - v[t[0]], v[t[2]] - v[t[0]])
                f.append(t if n @ outward[j] > 0 else [t[0], t[2], t[1]])
    return v, np.array(f, np.int64)


def _slab_region(with_top_points: bool = True):
    """A wall (y = 0, street at y < 0) under a roof slab that overhangs by 0.6 m: soffit at z = 5.75, fascia,
    top at z = 6.0. The MLS sees the wall (15 cm off the mesh), the soffit and, sloping towards the street as a
    pitched roof does, part of the top over the overhang. Returns (RegionInput, (m,) bool overhang top faces)."""
    from tasks.repair.region_geometry import RegionInput

    prof, outs = [], []
    for (y0, z0), (y1, z1), out, step in (((0, 0), (0, 5.75), (0, -1, 0), 0.25), ((0, 5.75), (-0.6, 5.75), (0, 0, -1), 0.1),
                                          ((-0.6, 5.75), (-0.6, 6.0), (0, -1, 0), 0.25), ((-0.6, 6.0), (2.0, 6.0), (0, 0, 1), 0.1)):
        n = max(1, round(np.hypot(y1 - y0, z1 - z0) / step))
        prof += [(y0 + (y1 - y0) * k / n, z0 + (z1 - z0) * k / n) for k in range(n)]
        outs += [out] * n
    prof.append((2.0, 6.0))
    v, f = _profile_mesh(np.array(prof), np.array(outs, float), np.linspace(0, 8, 33))
    rng = np.random.default_rng(3)
    wall = np.c_[rng.uniform(0, 8, 20000), rng.normal(-0.15, 0.004, 20000), rng.uniform(0.0, 5.6, 20000)]
    soffit = np.c_[rng.uniform(0, 8, 6000), rng.uniform(-0.6, -0.15, 6000), rng.normal(5.75, 0.004, 6000)]
    top = np.c_[rng.uniform(0, 8, 1500), rng.uniform(-0.6, 0.3, 1500), rng.normal(6.0, 0.004, 1500)]
    mls = np.concatenate([wall, soffit] + ([top] if with_top_points else []))
    data = RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=f, context_faces=np.zeros((0, 3), np.int64),
                       near_zone=np.ones(len(v), bool), mls_xyz=mls, mls_class=np.zeros(len(mls), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=None)
    c = v[f].mean(axis=1)
    return data, (c[:, 2] > 5.99) & (c[:, 1] < 0)


def _slab_area(geo) -> float:
    """Area (m²) of rebuilt faces inside the roof slab over the overhang (between soffit and top)."""
    t = geo.mesh.xyz[geo.mesh.faces]
    c = t.mean(axis=1)
    a = 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    return float(a[(c[:, 1] < -0.05) & (c[:, 1] > -0.55) & (c[:, 2] > 5.8) & (c[:, 2] < 5.95)].sum())


def test_points_on_a_kept_roofs_top_are_not_folded_into_the_soffit_under_it():
    """Real-density diagnosis (held-out 9103 at MLS density 1.0): the MLS sees a pitched roof's top over the
    eave; the top is kept, so those points were mapped onto the nearest chart (the soffit 25 cm under it) and
    triangulated into it, a zigzag through the slab. The retained surface explains them now; without the rule
    (retained_point_m 0) the slab fills with rebuilt faces, so the test can fail."""
    from tasks.repair.region_geometry import repair_region_geometry

    data, top = _slab_region()
    geo = repair_region_geometry(data, RepairConfig())
    assert not geo.replaced[top].any() and geo.stats["on_retained"] > 1000
    assert _slab_area(geo) < 1.0
    assert geo.replaced[~top].mean() > 0.5  # the wall and soffit are still rebuilt
    off = repair_region_geometry(data, RepairConfig.model_validate({"mesh": {"retained_point_m": 0,
                                                                             "drop_unsupported_m": 0}}))
    assert _slab_area(off) > 5.0
    dropped = repair_region_geometry(data, RepairConfig.model_validate({"mesh": {"retained_point_m": 0}}))
    assert _slab_area(dropped) < 0.5 * _slab_area(off)  # most of that zigzag rests on no surface: dropped
    none = repair_region_geometry(_slab_region(with_top_points=False)[0], RepairConfig())
    assert none.stats["on_retained"] == 0 and _slab_area(none) < 1.0  # no top points: nothing to explain


def test_on_retained_takes_points_on_a_kept_face_not_beyond_its_rim_nor_near_the_rebuild():
    """One plane, its x < 1 half kept and its x > 1 half to rebuild: a point on the kept half is explained by
    it, one within the tolerance of the rebuilt half is not, nor one beyond the kept rim or too far above."""
    from tasks.repair.keep import on_retained

    v, f = _grid(0, 2, 0, 2, 0.0)
    c = v[f].mean(axis=1)
    kept, rebuild = f[c[:, 0] < 1], f[c[:, 0] > 1]
    pts = np.array([[0.5, 1.0, 0.01],    # on the kept half, 0.5 m from the rebuild: explained
                    [0.95, 1.0, 0.01],   # on the kept half but 5 cm from the rebuild: stays in it
                    [1.5, 1.0, 0.01],    # on the rebuilt half
                    [0.5, -0.3, 0.0],    # beyond the kept rim, off to the side
                    [0.5, 1.0, 0.15]])   # 15 cm above: farther than the tolerance
    assert on_retained(pts, v, rebuild, kept, 0.1).tolist() == [True, False, False, False, False]
    assert not on_retained(pts, v, rebuild, kept, 0.0).any()
    assert on_retained(pts, v, rebuild, kept, 0.2).tolist()[:2] == [True, False]
