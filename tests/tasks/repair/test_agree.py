"""Zone faces the scan agrees with stay (tasks.repair.agree): a false alarm on a production's typical
topology rebuilds nothing, and a hole is rebuilt with a ring around it, the rest of the zone verbatim."""

from __future__ import annotations

import numpy as np

from tasks.config.repair import RepairConfig
from tasks.geometry.triangles import face_areas
from tasks.repair.region_geometry import RegionInput, repair_region_geometry


def _wall(x0: float, x1: float, nx: int, y: float = 0.0, height: float = 3.0, nz: int = 12):
    """A wall in the x-z plane at y, normal towards -y (the street): (vertices, faces)."""
    xs, zs = np.linspace(x0, x1, nx + 1), np.linspace(0, height, nz + 1)
    v = np.array([[x, y, z] for x in xs for z in zs])
    idx = lambda i, j: i * (nz + 1) + j
    f = [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)] for i in range(nx) for j in range(nz)]
    f += [[idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)] for i in range(nx) for j in range(nz)]
    return v, np.array(f, np.int64)


def _production():
    """A 10 m wall as a production holds it: two nodes meeting at x = 5 with duplicated vertices (an open
    seam), slivers along the seam, and a hidden layer 10 cm behind the second node (two nodes overlapping)."""
    parts = [_wall(0, 5, 25), _wall(5, 10, 31), _wall(6, 9, 9, y=0.1)]
    v, f, n = [], [], 0
    for pv, pf in parts:
        v.append(pv)
        f.append(pf + n)
        n += len(pv)
    v, f = np.concatenate(v), np.concatenate(f)
    sliver = np.array([[5.0, -0.001, 0.0], [5.0, -0.001, 3.0], [5.0005, -0.001, 1.5]])
    return np.concatenate([v, sliver]), np.concatenate([f, [[n, n + 2, n + 1]]])


def _scan(rng):
    """Street points on y = 0 (1 cm noise, ~2 cm spacing) over the whole wall, holes in the mesh included."""
    return np.c_[rng.uniform(0, 10, 60000), rng.normal(0, 0.01, 60000), rng.uniform(0.05, 2.95, 60000)]


def _region(v, f, pts):
    return RegionInput(xyz=v, vertex_id=np.arange(len(v)), zone_faces=f, context_faces=np.zeros((0, 3), np.int64),
                       near_zone=np.ones(len(v), bool), mls_xyz=pts, mls_class=np.zeros(len(pts), np.uint8),
                       ctx_xyz=np.zeros((0, 3)), face_normals=None)


EDGE = {"max_hole_loop_m": 10.0}  # the free-standing wall's outline is the mesh's edge, not a hole


def test_a_false_alarm_on_a_productions_topology_rebuilds_nothing():
    v, f = _production()
    data = _region(v, f, _scan(np.random.default_rng(1)))
    geo = repair_region_geometry(data, RepairConfig.model_validate({"mesh": EDGE}))
    assert not geo.replaced.any() and geo.mesh.n_faces == 0, geo.stats.get("plan")
    assert geo.stats["agreeing"]["unexplained_points"] == 0
    assert "agrees" in geo.stats["plan"]
    # the whole-zone rebuild (keep_agreeing_m 0) does replace it: the rule above is what keeps it
    old = repair_region_geometry(data, RepairConfig.model_validate({"mesh": EDGE | {"keep_agreeing_m": 0}}))
    assert old.replaced.any()


def test_a_hole_is_rebuilt_with_its_ring_and_the_rest_stays_verbatim():
    v, f = _wall(0, 10, 50)
    c = v[f].mean(axis=1)
    in_hole = (np.abs(c[:, 0] - 5.0) < 0.6) & (np.abs(c[:, 2] - 1.5) < 0.6)
    f = f[~in_hole]
    data = _region(v, f, _scan(np.random.default_rng(2)))
    geo = repair_region_geometry(data, RepairConfig.model_validate({"mesh": EDGE}))
    c = v[f].mean(axis=1)
    ring = (np.abs(c[:, 0] - 5.0) < 0.6 + 0.5 + 0.3) & (np.abs(c[:, 2] - 1.5) < 0.6 + 0.5 + 0.3)
    assert geo.replaced.any() and not geo.replaced[~ring].any()  # only faces near the hole are rebuilt
    assert geo.replaced[np.abs(c[:, 0] - 5.0) < 0.7].any()
    m = geo.mesh
    mc = m.xyz[m.faces].mean(axis=1)
    a = face_areas(m.xyz, m.faces, np.float64)
    filled = a[(np.abs(mc[:, 0] - 5.0) < 0.6) & (np.abs(mc[:, 2] - 1.5) < 0.6)].sum()
    assert filled > 0.8 * 1.2 * 1.2  # the hole is covered by the rebuild
    assert np.abs(mc[:, 1]).max() < 0.05  # on the wall


def test_no_chord_spans_what_neither_the_scan_nor_the_input_shows():
    """A hole whose upper part the scanner never saw (occluded): the rebuild fills the seen part; faces
    across the unseen part rest on no surface the evidence shows (no scan point within 30 cm, no input
    face: tasks.repair.support.unsupported_faces), so it is left open; without the rule it is spanned."""
    v, f = _wall(0, 10, 50)
    c = v[f].mean(axis=1)
    hole = (np.abs(c[:, 0] - 5.0) < 1.0) & (np.abs(c[:, 2] - 1.5) < 1.0)
    f = f[~hole]
    pts = _scan(np.random.default_rng(3))
    gap = (np.abs(pts[:, 0] - 5.0) < 1.0) & (pts[:, 2] > 1.2) & (pts[:, 2] < 2.5)
    pts = pts[~gap]
    data = _region(v, f, pts)
    for drop, most in ((0.05, 0.2), (0.0, None)):  # 0.2: a weld face to the border above stays
        geo = repair_region_geometry(data, RepairConfig.model_validate({"mesh": EDGE | {"drop_unsupported_m": drop}}))
        m = geo.mesh
        mc = m.xyz[m.faces].mean(axis=1)
        a = face_areas(m.xyz, m.faces, np.float64)
        in_gap = (np.abs(mc[:, 0] - 5.0) < 0.6) & (mc[:, 2] > 1.6) & (mc[:, 2] < 2.1)  # >= 0.4 m from the scan
        seen = (np.abs(mc[:, 0] - 5.0) < 0.8) & (mc[:, 2] > 0.6) & (mc[:, 2] < 1.1)
        assert a[seen].sum() > 0.8 * 1.6 * 0.5  # the seen part of the hole is filled either way
        if most is not None:
            assert a[in_gap].sum() < most and geo.stats["unsupported_faces_dropped"] > 0
        else:
            assert a[in_gap].sum() > 0.3  # the chords: what the rule removes
