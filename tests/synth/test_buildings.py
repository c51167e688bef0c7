"""Truth campus geometry: layout, walls, windows, eaves, occluders (synth.layout, synth.facades, synth.buildings,
synth.occluders)."""

import numpy as np
import pytest

from synth.buildings import make_scene
from synth.envelope import edge_normals_2d
from synth.layout import LayoutParams, road_lines
from synth.scene import FaceClass, OccluderClass

EXTENT = (0.0, 0.0, 160.0, 160.0)


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(7), EXTENT, 5, storeys=(1, 8), occluder_density=2.0)


def _inside_polygon(p, poly):
    """Even-odd test of points p (n, 2) against polygon (k, 2)."""
    a, b = poly, np.roll(poly, -1, axis=0)
    cross = (a[:, 1] > p[:, 1:2]) != (b[:, 1] > p[:, 1:2])
    dy = np.where(b[:, 1] == a[:, 1], 1e-300, b[:, 1] - a[:, 1])
    x = a[:, 0] + (p[:, 1:2] - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
    return np.count_nonzero(cross & (p[:, :1] < x), axis=1) % 2 == 1


def test_deterministic_per_seed():
    a = make_scene(np.random.default_rng(3), (0, 0, 120, 120), 3)
    b = make_scene(np.random.default_rng(3), (0, 0, 120, 120), 3)
    c = make_scene(np.random.default_rng(4), (0, 0, 120, 120), 3)
    for x, y in ((a.truth, b.truth), (a.occluders.mesh, b.occluders.mesh)):
        assert np.array_equal(x.vertices, y.vertices) and np.array_equal(x.faces, y.faces)
        assert np.array_equal(x.face_class, y.face_class) and np.array_equal(x.face_color, y.face_color)
    assert a.meta["cars"] == b.meta["cars"]
    assert a.truth.vertices.shape != c.truth.vertices.shape or not np.array_equal(a.truth.vertices, c.truth.vertices)


def test_buildings_inside_extent_and_apart(scene):
    assert len(scene.buildings) == 5
    m = scene.truth
    v = m.vertices[np.unique(m.faces[m.face_building >= 0])]
    assert v[:, 0].min() >= EXTENT[0] and v[:, 1].min() >= EXTENT[1]
    assert v[:, 0].max() <= EXTENT[2] and v[:, 1].max() <= EXTENT[3]
    boxes = []
    for b in scene.buildings:  # the xy box of everything the building owns: walls, eaves, balconies
        p = m.vertices[np.unique(m.faces[m.face_building == b.id])]
        boxes.append((p[:, 0].min(), p[:, 1].min(), p[:, 0].max(), p[:, 1].max()))
    for i in range(len(boxes)):
        for j in range(i + 1, len(boxes)):
            p, q = boxes[i], boxes[j]
            gap = max(q[0] - p[2], p[0] - q[2], q[1] - p[3], p[1] - q[3])
            assert gap >= LayoutParams().gap_m - 1e-9


def test_front_facades_at_street_range(scene):
    roads = scene.meta["roads"]
    for d in scene.meta["buildings"]:
        f = d["front_normal"]
        assert f is not None
        ax = 0 if f[0] != 0 else 1
        face = d["bbox"][ax] if f[ax] < 0 else d["bbox"][ax + 2]
        dist = min(abs(face - c) for a, c, hw in roads if a == ax)
        assert 4.0 - 1e-9 <= dist <= 15.0 + 1e-9


def test_roads_line_up_across_tiles():
    left = make_scene(np.random.default_rng(1), (0, 0, 150, 150), 2)
    right = make_scene(np.random.default_rng(2), (150, 0, 300, 150), 2)
    assert [r for r in left.meta["roads"] if r[0] == 1] == [r for r in right.meta["roads"] if r[0] == 1]
    wide = road_lines((-200, 0, 500, 150))  # a road's width depends on the global grid only
    assert all(r in wide for r in road_lines((150, 0, 300, 150)))

    def road_edge_ys(s):  # y of ROAD vertices on the shared border x = 150
        m = s.truth
        v = m.vertices[np.unique(m.faces[m.face_class == FaceClass.ROAD])]
        return np.unique(np.round(v[np.isclose(v[:, 0], 150.0), 1], 9))

    ys = road_edge_ys(left)
    assert len(ys) >= 2 and np.array_equal(ys, road_edge_ys(right))


def test_walls_face_outwards_and_no_duplicate_faces(scene):
    m = scene.truth
    n, c = m.face_normals(), m.triangles().mean(axis=1)
    for b in scene.buildings:
        w = (m.face_building == b.id) & (m.face_class == FaceClass.WALL) & (np.abs(n[:, 2]) < 0.1)
        out = _inside_polygon((c[w] + 0.05 * n[w])[:, :2], b.footprint)
        inn = _inside_polygon((c[w] - 0.05 * n[w])[:, :2], b.footprint)
        assert not out.any() and inn.all()
    key = np.round(np.column_stack([c, n]), 6)
    assert len(np.unique(key, axis=0)) == len(key)
    assert len(np.unique(np.sort(m.faces, axis=1), axis=0)) == m.n_faces


def test_window_recess_depth(scene):
    m = scene.truth
    n, c = m.face_normals(), m.triangles().mean(axis=1)
    for b, d in zip(scene.buildings, scene.meta["buildings"]):
        assert 0.1 <= d["recess_m"] <= 0.3
        g = np.flatnonzero((m.face_building == b.id) & (m.face_class == FaceClass.GLASS))
        assert len(g)
        en = edge_normals_2d(b.footprint)
        depth = np.full(len(g), np.inf)
        for i in range(len(b.footprint)):
            a2, b2 = b.footprint[i], b.footprint[(i + 1) % len(b.footprint)]
            t = (b2 - a2) / np.linalg.norm(b2 - a2)
            rel = c[g, :2] - a2
            along = rel @ t
            facing = n[g, :2] @ en[i] > 0.99
            hit = facing & (along > 0) & (along < np.linalg.norm(b2 - a2))
            depth[hit] = np.minimum(depth[hit], -(rel[hit] @ en[i]))
        assert np.allclose(depth, d["recess_m"], atol=1e-9)
        assert np.any(m.face_class[m.face_building == b.id] == FaceClass.FRAME)


def test_eaves_overhang_from_below(scene):
    m = scene.truth
    n = m.face_normals()
    for b in scene.buildings:
        e = (m.face_building == b.id) & (m.face_class == FaceClass.EAVE)
        assert e.any() and np.all(n[e, 2] < -0.5)  # soffits are seen from below
        p = m.vertices[np.unique(m.faces[e])]
        lo, hi = b.footprint.min(axis=0), b.footprint.max(axis=0)
        assert np.allclose(lo - p[:, :2].min(axis=0), b.eave_overhang_m, atol=1e-6)
        assert np.allclose(p[:, :2].max(axis=0) - hi, b.eave_overhang_m, atol=1e-6)
        assert 0.3 <= b.eave_overhang_m <= 1.2


def test_occluders_clear_of_buildings(scene):
    o, m = scene.occluders.mesh, scene.truth
    kinds = set(o.face_class.tolist())
    assert {OccluderClass.TREE, OccluderClass.CAR, OccluderClass.PEDESTRIAN} <= kinds
    bv = m.vertices[np.unique(m.faces[m.face_building >= 0])]
    for rec in scene.meta["occluders"]:
        lo, hi = np.array(rec["bbox"][:3]) + 0.01, np.array(rec["bbox"][3:]) - 0.01
        assert not np.any(np.all((bv > lo) & (bv < hi), axis=1)), rec
    ov = o.vertices[o.faces.ravel()]
    for b, d in zip(scene.buildings, scene.meta["buildings"]):
        below = ov[:, 2] < d["top_z_m"]
        assert not _inside_polygon(ov[below, :2], b.footprint).any()


def test_cars_recorded_and_parked_on_the_road_edge(scene):
    cars = scene.meta["cars"]
    assert len(cars) >= 3
    o = scene.occluders.mesh
    roads = scene.meta["roads"]
    for car in cars:
        f = o.face_building == car["id"]
        assert np.all(o.face_class[f] == OccluderClass.CAR)
        p = o.vertices[o.faces[f].ravel()]
        assert np.allclose(p[:, :2].min(axis=0) + p[:, :2].max(axis=0), 2 * np.array(car["centre"][:2]))
        ext = p.max(axis=0) - p.min(axis=0)
        assert abs(ext[car["axis"]] - car["size"][0]) < 1e-6 and abs(ext[2] - car["size"][2]) < 1e-6
        lat = 1 - car["axis"]  # across the road
        off = [abs(car["centre"][lat] - c) - hw for a, c, hw in roads if a == lat]
        assert -1.4 - 1e-9 <= min(off, key=abs) <= -1.0 + 1e-9
