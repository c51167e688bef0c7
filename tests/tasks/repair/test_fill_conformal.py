"""Rebuilt charts on coarse-like zones: conformal chart map + constrained Delaunay, the unseen surface
kept, and the vertex-id namespace (split vertices are campus ids, new vertices never collide with them)."""

import numpy as np

from storage.vertex_ids import is_campus_id
from tasks.geometry.triangles import face_areas
from tasks.repair.chart import zone_charts
from tasks.repair.conformal import conformal_uv, constrained_triangles, signed_areas
from tasks.repair.fill import unseen_samples
from tasks.repair.mesh import rebuild_charts


def _band(length=30.0, height=3.0, nx=60, nz=6, y=0.0):
    """A vertical wall band in the x-z plane at y, as a grid of (nx x nz) quads: (vertices, faces)."""
    xs, zs = np.linspace(0, length, nx + 1), np.linspace(0, height, nz + 1)
    v = np.array([[x, y, z] for x in xs for z in zs])
    idx = lambda i, j: i * (nz + 1) + j
    f = []
    for i in range(nx):
        for j in range(nz):
            f += [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)], [idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]]
    return v, np.array(f, np.int64)


def _longest_edges(xyz, faces):
    t = xyz[faces]
    return np.linalg.norm(t - np.roll(t, 1, axis=1), axis=2).max(axis=1)


def test_conformal_map_of_a_planar_band_is_an_isometry():
    v, f = _band()
    topo = zone_charts(v, f, np.zeros((0, 3), np.int64), np.ones(len(v), bool), 40.0)
    ch = topo.charts[0]
    assert ch.cuv is not None
    d3 = np.linalg.norm(ch.xyz[:, None] - ch.xyz[None], axis=2)
    d2 = np.linalg.norm(ch.cuv[:, None] - ch.cuv[None], axis=2)
    assert np.abs(d3 - d2).max() < 1e-6
    assert (signed_areas(ch.cuv, ch.faces) > 0).all()
    # the unit-disc map squeezes the 10:1 band: distances along it shrink far more than across
    dd = np.linalg.norm(ch.uv[:, None] - ch.uv[None], axis=2)
    ratio = dd[d3 > 1] / d3[d3 > 1]
    assert ratio.max() / ratio.min() > 5


def test_conformal_map_refuses_a_degenerate_chart():
    v = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float)  # a zero-area face
    assert conformal_uv(v, np.array([[0, 1, 2]]), np.array([0, 1, 2])) is None


def test_constrained_triangles_keep_the_boundary_and_stay_inside_an_l_shape():
    loop = np.array([[0, 0], [4, 0], [4, 1], [1, 1], [1, 4], [0, 4]], float)
    inner = np.array([[0.5, 0.5], [2.5, 0.5], [0.5, 2.5], [3.0, 3.0]])  # the last lies in the notch, outside
    tri = constrained_triangles(np.concatenate([loop, inner]), len(loop))
    assert tri is not None
    assert 9 not in tri  # the outside point is left out
    c = np.concatenate([loop, inner])[tri].mean(axis=1)
    assert not ((c[:, 0] > 1) & (c[:, 1] > 1)).any()  # no triangle in the notch
    edges = {tuple(sorted(e)) for t in tri.tolist() for e in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0]))}
    assert all(tuple(sorted((i, (i + 1) % 6))) in edges for i in range(6))
    area = np.abs(signed_areas(np.concatenate([loop, inner]), tri)).sum()
    assert abs(area - 7.0) < 1e-9


def test_new_vertices_never_weld_onto_split_vertex_ids():
    """Split vertices (ingest, long faces) carry ids <= -2; points of the rebuild must not take them."""
    v, f = _band(nx=30, nz=3)
    split_like = -2 - np.arange(len(v), dtype=np.int64)  # the small negative ids a weld-by-position gave
    assert is_campus_id(split_like).all()
    topo = zone_charts(v, f, np.zeros((0, 3), np.int64), np.ones(len(v), bool), 40.0)
    g = np.stack(np.meshgrid(np.arange(0.25, 30, 0.5), np.arange(0.25, 3, 0.5)), -1).reshape(-1, 2)
    pts = np.c_[g[:, 0], np.full(len(g), 0.05), g[:, 1]]
    mesh = rebuild_charts(topo.charts, split_like, pts, np.ones(len(pts), np.int8), np.full(len(pts), -1),
                          max_map_distance_m=0.5, border_margin_m=0.02, max_edge_m=0.8)
    assert not is_campus_id(mesh.vertex_id[mesh.source == 1]).any()
    assert _longest_edges(mesh.xyz, mesh.faces).max() < 1.5
    assert abs(face_areas(mesh.xyz, mesh.faces, np.float64).sum() - 90.0) < 1.0


def test_unseen_half_of_a_zone_keeps_the_input_surface():
    v, f = _band(length=10.0, height=3.0, nx=10, nz=3)
    seen = np.array([[x, 0.2, z] for x in np.arange(0.05, 5, 0.1) for z in np.arange(0.05, 3, 0.1)])  # 0.2 m off
    fill = unseen_samples(v, f, seen, np.zeros((0, 3)), step_m=0.4, reach_m=1.0)
    assert len(fill) > 20
    assert fill[:, 0].min() > 5.0 - 0.4 and np.allclose(fill[:, 1], 0.0)
    # a replaced vertex is not put back: no sample near it
    fill2 = unseen_samples(v, f, seen, np.array([[8.0, 0.0, 1.0]]), step_m=0.4, reach_m=1.0)
    assert np.linalg.norm(fill2 - [8.0, 0.0, 1.0], axis=1).min() >= 0.4
    assert len(unseen_samples(v, f, seen, np.zeros((0, 3)), step_m=0.0, reach_m=1.0)) == 0


def test_points_far_from_every_face_are_meshed_on_their_own():
    """A passage wall inside a city model's block: no face within reach, so no chart takes its points;
    the free surface meshes them (new vertex ids, nothing replaced)."""
    import trimesh

    from tasks.config.repair import RepairConfig
    from tasks.repair.region_geometry import RegionInput, repair_region_geometry

    block = trimesh.creation.box(extents=(20.0, 12.0, 9.0))
    block.apply_translation((10.0, 6.0, 4.5))
    v, f = np.asarray(block.vertices, float), np.asarray(block.faces, np.int64)
    g = np.stack(np.meshgrid(np.arange(6.0, 12.0, 0.05), np.arange(0.2, 2.8, 0.05)), -1).reshape(-1, 2)
    wall = np.c_[g[:, 0], np.full(len(g), 4.0), g[:, 1]]  # 4 m inside the block's front
    data = RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=np.zeros((0, 3), np.int64), context_faces=f,
                       near_zone=np.zeros(len(v), bool), mls_xyz=wall, mls_class=np.zeros(len(wall), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=np.asarray(block.face_normals, np.float32))
    geo = repair_region_geometry(data, RepairConfig())
    m = geo.mesh
    area = face_areas(m.xyz, m.faces, np.float64).sum()
    assert 0.8 * 6 * 2.6 < area < 1.2 * 6 * 2.6
    assert np.abs(m.xyz[:, 1] - 4.0).max() < 0.05
    assert not is_campus_id(m.vertex_id).any() and not geo.replaced.any()
    off = RepairConfig.model_validate({"mesh": {"free_surface": False}})
    assert repair_region_geometry(data, off).mesh.n_faces == 0


def _half_seen_region():
    """A 10 m x 3 m wall zone whose left half the MLS sees 0.5 m behind it (a recess), right half unseen."""
    from tasks.repair.region_geometry import RegionInput

    v, f = _band(length=10.0, height=3.0, nx=20, nz=6)
    seen = np.array([[x, 0.5, z] for x in np.arange(0.02, 5, 0.04) for z in np.arange(0.02, 3, 0.04)])
    return RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=f, context_faces=np.zeros((0, 3), np.int64),
                       near_zone=np.ones(len(v), bool), mls_xyz=seen, mls_class=np.zeros(len(seen), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=None)


def test_unseen_part_keeps_the_input_and_unsupported_rebuilds_fall_back():
    from tasks.config.repair import RepairConfig
    from tasks.repair.region_geometry import repair_region_geometry

    data = _half_seen_region()
    # the fill path: every zone face rebuilt (no input face kept as unseen, agreeing, or under a dropped chord)
    cfg = RepairConfig.model_validate({"mesh": {"keep_unseen_m": 0, "keep_agreeing_m": 0, "restore_dropped_m": 0}})
    geo = repair_region_geometry(data, cfg)
    m = geo.mesh
    assert m.n_faces and geo.replaced.all()
    c = m.xyz[m.faces].mean(axis=1)
    right = c[:, 0] > 6.0  # beyond the step (the fill keeps a step's clearance from the seen half)
    assert np.abs(c[right, 1]).max() < 0.02  # the unseen half stays on the input wall
    inner = (c[:, 0] > 0.5) & (c[:, 0] < 4.0) & (c[:, 2] > 0.5) & (c[:, 2] < 2.5)  # off the zone's fixed edge
    assert np.mean(np.abs(c[inner, 1] - 0.5) < 0.05) > 0.99  # the seen half moves onto the MLS surface
    share = geo.stats["unsupported_share"]
    assert 0 < share < 0.3  # only the step between the two halves rests on neither
    strict = repair_region_geometry(data, RepairConfig.model_validate({"mesh": {"max_unsupported_share": share / 2,
                                                                                "keep_unseen_m": 0,
                                                                                "keep_agreeing_m": 0}}))
    assert strict.mesh.n_faces == 0 and not strict.replaced.any()
    assert strict.stats["plan"].startswith("fallback")


def test_points_in_front_of_the_surface_are_never_meshed_freely():
    """A tree or a car in front of a facade (far from the mesh, in front of it) is not the building."""
    import trimesh

    from tasks.config.repair import RepairConfig
    from tasks.repair.region_geometry import RegionInput, repair_region_geometry

    block = trimesh.creation.box(extents=(20.0, 12.0, 9.0))
    block.apply_translation((10.0, 6.0, 4.5))
    v, f = np.asarray(block.vertices, float), np.asarray(block.faces, np.int64)
    g = np.stack(np.meshgrid(np.arange(6.0, 12.0, 0.05), np.arange(0.5, 2.8, 0.05)), -1).reshape(-1, 2)
    tree = np.c_[g[:, 0], np.full(len(g), -3.0), g[:, 1]]  # 3 m in front of the block's front face
    data = RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=np.zeros((0, 3), np.int64), context_faces=f,
                       near_zone=np.zeros(len(v), bool), mls_xyz=tree, mls_class=np.zeros(len(tree), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=np.asarray(block.face_normals, np.float32))
    assert repair_region_geometry(data, RepairConfig()).mesh.n_faces == 0


def _edge_is_mesh_edge():
    from tasks.config.repair import RepairConfig

    # a free-standing test band's outline (26 m) would count as a hole to fill; in a campus it is the mesh's edge
    return RepairConfig.model_validate({"mesh": {"max_hole_loop_m": 5.0}})


EDGE_IS_MESH_EDGE = _edge_is_mesh_edge()


def test_unseen_zone_faces_stay_verbatim_and_the_rebuild_stitches_to_them():
    """The default: the unseen half of the zone is not rebuilt at all; its faces stay, and the rebuilt half
    welds to their vertices (no gap)."""
    from tasks.repair.region_geometry import repair_region_geometry

    data = _half_seen_region()
    unseen_only = EDGE_IS_MESH_EDGE.model_copy(update={"mesh": EDGE_IS_MESH_EDGE.mesh.model_copy(
        update={"keep_agreeing_m": 0.0})})
    geo = repair_region_geometry(data, unseen_only)
    c_in = data.xyz[data.zone_faces].mean(axis=1)
    kept = ~geo.replaced
    assert geo.stats["kept_unseen_faces"] == kept.sum() > 0
    default = repair_region_geometry(data, EDGE_IS_MESH_EDGE)  # faces the scan says nothing against stay too
    assert (~default.replaced >= kept).all() and c_in[default.replaced, 0].max() < 5.0 + 0.5 + 0.5
    assert default.stats["agreeing"]["unexplained_points"] > 0
    assert c_in[kept, 0].min() > 5.0 and (c_in[:, 0] > 6.0).sum() <= kept.sum()  # only, and all of, the far half
    m = geo.mesh
    c = m.xyz[m.faces].mean(axis=1)
    assert c[:, 0].max() < 6.0  # nothing rebuilt over the kept faces
    assert geo.stats["border"]["max_gap_m"] < 1e-6
    kept_v = np.unique(data.zone_faces[kept])
    shared = np.intersect1d(m.vertex_id, data.vertex_id[kept_v])
    assert len(shared) >= 5  # the seam between the halves is welded by id


def _wall_and_roof(seed: int):
    """A zone over a wall's top storey (x-z plane at y = 0, z in [0, 3]) and a flat roof behind it at z = 3,
    with street MLS points 15 cm in front of the wall only: (RegionInput, (m,) bool roof faces)."""
    from tasks.repair.region_geometry import RegionInput

    wv, wf = _band(length=8.0, height=3.0, nx=16, nz=6)
    rv = np.array([[x, y, 3.0] for x in np.linspace(0, 8, 17) for y in np.linspace(0, 3, 7)])
    idx = lambda i, j: len(wv) + i * 7 + j
    rf = [[idx(i, j), idx(i + 1, j + 1), idx(i + 1, j)] for i in range(16) for j in range(6)]
    rf += [[idx(i, j), idx(i, j + 1), idx(i + 1, j + 1)] for i in range(16) for j in range(6)]
    v, f = np.concatenate([wv, rv]), np.concatenate([wf, np.array(rf, np.int64)])
    rng = np.random.default_rng(seed)
    wall_pts = np.c_[rng.uniform(0, 8, 6000), rng.normal(0.15, 0.005, 6000), rng.uniform(0, 2.9, 6000)]
    data = RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=f, context_faces=np.zeros((0, 3), np.int64),
                       near_zone=np.ones(len(v), bool), mls_xyz=wall_pts, mls_class=np.zeros(len(wall_pts), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=None)
    return data, np.arange(len(f)) >= len(wf)


def test_a_roof_strip_in_a_facade_zone_is_never_rebuilt():
    """A zone over a wall's top storey takes a strip of the roof with it. The street MLS sees the wall
    only: the roof faces come out exactly as they went in, and no rebuilt triangle cuts across the eave."""
    from tasks.repair.region_geometry import repair_region_geometry

    data, roof = _wall_and_roof(seed=0)
    v, f = data.xyz, data.zone_faces
    geo = repair_region_geometry(data, EDGE_IS_MESH_EDGE)
    cz = v[f].mean(axis=1)
    deep_roof = roof & (cz[:, 1] > 1.2)  # every vertex more than clear_m back from the scanned wall top
    assert (~geo.replaced[deep_roof]).all()
    assert geo.replaced[~roof & (cz[:, 2] < 2.0)].all()  # the seen wall is rebuilt
    m = geo.mesh
    c = m.xyz[m.faces].mean(axis=1)
    assert not ((c[:, 1] > 1.2) & (c[:, 2] > 2.5)).any()  # nothing rebuilt over the kept roof
    mid = (c[:, 2] > 0.5) & (c[:, 2] < 2.0) & (c[:, 0] > 0.5) & (c[:, 0] < 7.5)
    assert np.median(np.abs(c[mid, 1] - 0.15)) < 0.02  # the wall moved onto the scan


def test_a_scanned_wall_top_beside_a_roof_edge_does_not_contradict_it():
    """Conflicts need the contradicting point on the vertex's normal line (a 45° cone), not off to the side."""
    from tasks.repair.region_geometry import in_view

    wall = np.array([[x, 0.0, z] for x in np.arange(0, 2, 0.05) for z in np.arange(2.0, 2.9, 0.05)])  # y = 0 wall top
    roof_edge = np.array([[1.0, 0.3, 3.0]])  # 0.3 m behind the wall plane, 0.1 m above its top: normal up
    facade = np.array([[1.0, 0.25, 2.5]])  # 0.25 m in front of the wall: normal along y
    up, along_y = np.array([[0, 0, 1.0]]), np.array([[0, 1.0, 0]])
    assert not in_view(roof_edge, up, wall, radius_m=0.5, cone_deg=45)[0]
    assert in_view(roof_edge, up, wall, radius_m=0.5, cone_deg=90)[0]  # the old rule: anything within 0.5 m
    assert in_view(facade, along_y, wall, radius_m=0.5, cone_deg=45)[0]
    assert not in_view(facade, along_y, wall[:0], radius_m=0.5, cone_deg=45)[0]


def test_front_rule_runs_and_cuts_only_what_stands_in_front():
    """typed.front_m > 0: vertices beyond conflict_radius_m from the scan but in front of it (between the
    scanner and the scanned wall: the mesh of a recess) are cut; a mesh behind the scan is not."""
    from dataclasses import replace

    from tasks.config.repair import RepairConfig
    from tasks.repair.region_geometry import repair_region_geometry

    data = _half_seen_region()  # the mesh (normal towards -y, the street) stands 0.5 m in front of the scan
    cfg = RepairConfig.model_validate({"typed": {"front_m": 0.3}, "mesh": {"keep_unseen_m": 0, "keep_agreeing_m": 0}})
    geo = repair_region_geometry(data, cfg)
    assert geo.stats["in_front"] > 0 and geo.mesh.n_faces
    behind = replace(data, mls_xyz=data.mls_xyz * [1, -1, 1])  # the same scan 0.5 m on the street side
    assert repair_region_geometry(behind, cfg).stats["in_front"] == 0


def test_a_wall_facing_away_does_not_contradict_a_roof_vertex_above_it():
    """A roof edge flush with the wall: the wall's points lie straight below it, in the cone, but face the
    street, not the sky. Only a parallel surface displaced contradicts a vertex (typed.conflict_min_cos)."""
    from tasks.repair.region_geometry import in_view

    wall = np.array([[x, 0.0, z] for x in np.arange(0, 2, 0.05) for z in np.arange(2.5, 2.95, 0.05)])
    wall_n = np.tile([0, -1.0, 0], (len(wall), 1))
    roof_edge, up = np.array([[1.0, 0.02, 3.0]]), np.array([[0, 0, 1.0]])
    assert in_view(roof_edge, up, wall, radius_m=0.5, cone_deg=45)[0]  # orientation ignored: contradicted
    assert not in_view(roof_edge, up, wall, radius_m=0.5, cone_deg=45, pts_n=wall_n, min_cos=0.7)[0]
    lower_roof = wall * [1, 1, 0] + [0, 0, 2.7]  # a parallel roof 0.3 m below: that does contradict it
    assert in_view(roof_edge, up, lower_roof, radius_m=0.5, cone_deg=45, pts_n=np.tile([0, 0, 1.0], (len(wall), 1)),
                   min_cos=0.7)[0]

