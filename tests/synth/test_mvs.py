"""Simulated photogrammetry mesh, its defects and texture atlas (synth.mvs / synth.defects / synth.texture)."""

import numpy as np
import pytest

from synth.buildings import make_scene
from synth.defects import DEFECT_TYPES, HOLE_CLASSES, HOLE_TYPES, facade_patch_bad_fraction
from synth.lattice import strip_chart
from synth.mvs import MvsParams, make_mvs_mesh
from synth.scene import FaceClass, Mesh
from synth.texture import bake_atlas

FACADE = [FaceClass.WALL, FaceClass.GLASS, FaceClass.FRAME, FaceClass.BALCONY]


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(3), (0.0, 0.0, 100.0, 100.0), 2, storeys=(2, 5), occluder_density=2.0)


@pytest.fixture(scope="module")
def mvs(scene):
    return make_mvs_mesh(np.random.default_rng(1), scene)


@pytest.fixture(scope="module")
def clean(scene):
    """The same lattice without defects (the rng draws before the defect stage are the same)."""
    return make_mvs_mesh(np.random.default_rng(1), scene, MvsParams(defects=None))[0]


def _edges(m):
    return np.linalg.norm(m.vertices[m.faces[:, [1, 2, 0]]] - m.vertices[m.faces], axis=2)


def test_strip_chart_tiles_polygon_exactly():
    rng = np.random.default_rng(0)
    for poly in ([[0, 0, 0], [10, 0, 0], [10, 0, 6], [0, 0, 6]], [[0, 0, 5], [10, 0, 5], [5, 0, 8]],
                 [[0, 0, 0], [3, 0, 0], [10, 0, 0], [9, 1, 0], [1, 1, 0]]):
        poly = np.array(poly, float)
        v, f, b = strip_chart(poly, [0.1] * len(poly), 0.12, rng)
        t = v[f]
        cr = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        n = np.cross(poly[1] - poly[0], poly[-1] - poly[0])
        n /= np.linalg.norm(n)
        area = 0.5 * np.linalg.norm(np.sum([np.cross(poly[i], poly[(i + 1) % len(poly)]) for i in range(len(poly))],
                                           axis=0))
        assert np.all(cr @ n > 0)  # every triangle wound like the polygon
        assert 0.5 * (cr @ n).sum() == pytest.approx(area, rel=1e-9)  # no gap, no overlap
        on_edge = v[b]  # boundary samples lie on the outline, at most 0.1 m apart along each edge
        assert len(on_edge) >= sum(np.ceil(np.linalg.norm(poly[(i + 1) % len(poly)] - poly[i]) / 0.1)
                                   for i in range(len(poly)))


def test_deterministic(scene, mvs):
    m2, d2 = make_mvs_mesh(np.random.default_rng(1), scene)
    m, d = mvs
    assert np.array_equal(m.vertices, m2.vertices) and np.array_equal(m.faces, m2.faces)
    assert np.array_equal(m.face_class, m2.face_class) and d == d2
    m3, _ = make_mvs_mesh(np.random.default_rng(2), scene, MvsParams(defects=None))
    assert m3.vertices.shape != m.vertices.shape or not np.allclose(m3.vertices, m.vertices)


def test_resolution_like_contextcapture(clean):
    m = clean
    fac = np.isin(m.face_class, FACADE) & (m.face_building >= 0)
    e = _edges(m)[fac]
    p10, p50, p90 = np.percentile(e, [10, 50, 90])
    assert 0.08 <= p50 <= 0.16 and p10 > 0.05 and p90 < 0.25
    density = fac.sum() / m.face_areas()[fac].sum()
    assert 110 <= density <= 220  # faces per m^2 of facade (real ContextCapture: ~160)
    valence = np.bincount(m.faces.ravel(), minlength=len(m.vertices))
    assert (valence == 6).mean() > 0.85


def test_watertight_but_for_the_extent_border(scene, clean):
    f = clean.faces
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    assert c.max() == 2  # manifold
    mid = clean.vertices[u[c == 1]].mean(axis=1)
    x0, y0, x1, y1 = scene.extent
    border = np.minimum.reduce([np.abs(mid[:, 0] - x0), np.abs(mid[:, 0] - x1), np.abs(mid[:, 1] - y0),
                                np.abs(mid[:, 1] - y1)])
    assert border.max() < 0.1


def test_classes_carried_over(scene, clean):
    m = clean
    ids = {b.id for b in scene.buildings}
    assert set(np.unique(m.face_building).tolist()) == ids | {-1}
    terrain = m.face_building < 0
    assert set(np.unique(m.face_class[terrain]).tolist()) <= {FaceClass.GROUND, FaceClass.ROAD}
    for cls in (FaceClass.WALL, FaceClass.GLASS, FaceClass.ROOF, FaceClass.EAVE, FaceClass.ROAD):
        assert np.any(m.face_class == cls)


def test_recesses_partly_filled(scene, clean):
    m = clean
    c = m.triangles().mean(axis=1)
    for b, d in zip(scene.buildings, scene.meta["buildings"]):
        g = (m.face_building == b.id) & (m.face_class == FaceClass.GLASS)
        lo, hi = b.footprint.min(axis=0), b.footprint.max(axis=0)
        # depth behind the nearest wall plane of the (axis-aligned) footprint bbox
        depth = np.minimum.reduce([c[g, 0] - lo[0], hi[0] - c[g, 0], c[g, 1] - lo[1], hi[1] - c[g, 1]])
        ratio = np.median(depth) / d["recess_m"]
        assert 0.3 < ratio < 0.9


def test_defects_recorded_and_valid(mvs):
    m, defects = mvs
    assert {x["type"] for x in defects} == set(DEFECT_TYPES)
    assert [x["id"] for x in defects] == list(range(len(defects)))
    for d in defects:
        f = np.asarray(d["faces"], np.int64)
        s = np.asarray(d["samples"])
        assert len(s) and s.shape[1] == 3
        assert np.allclose(d["bbox"], [*s.min(axis=0), *s.max(axis=0)])
        if d["type"] in HOLE_TYPES:
            assert len(f) == 0
            continue
        assert len(f) and f.min() >= 0 and f.max() < m.n_faces and len(np.unique(f)) == len(f)
        assert np.all(m.face_building[f] == d["building"])
        reach = d["radius_m"] + 2.0
        assert np.linalg.norm(m.vertices[m.faces[f]].mean(axis=1) - d["centre"], axis=1).max() < reach
        lo, hi = {"protrusion": (0.2, 1.0), "melted_eave": (0.2, 1.0), "recess": (0.1, 0.5), "dent": (0.1, 0.5),
                  "warp": (0.1, 0.35)}[d["type"]]
        assert lo <= d["magnitude_m"] <= hi


def test_holes_have_no_faces(mvs, clean):
    m, defects = mvs
    holes = [d for d in defects if d["type"] in HOLE_TYPES]
    assert {d["type"] for d in holes} == set(HOLE_TYPES)

    cen = {id(x): x.triangles().mean(axis=1) for x in (m, clean)}

    def in_hole(mesh, d):
        rel = cen[id(mesh)] - d["centre"]
        dn = rel @ np.array(d["normal"])
        r = np.hypot(rel @ np.array(d["axis_u"]), rel[:, 2])
        return (np.isin(mesh.face_class, HOLE_CLASSES) & (mesh.face_building == d["building"]) & (r < d["radius_m"])
                & (dn > -d["back_m"]) & (dn < d["front_m"]))

    removed = 0
    for d in holes:
        assert not in_hole(m, d).any()
        assert in_hole(clean, d).sum() > 20  # the defect-free mesh had surface there
        removed += in_hole(clean, d).sum()
        s = np.asarray(d["samples"])  # the removed truth surface, on the wall disc
        rel = s - d["centre"]
        assert np.hypot(rel @ np.array(d["axis_u"]), rel[:, 2]).max() < d["radius_m"] + 1e-3  # samples: 0.1 mm
    assert clean.n_faces - m.n_faces >= 0.9 * removed


def test_bad_patch_fraction(mvs):
    m, defects = mvs
    assert 0.3 <= facade_patch_bad_fraction(m, defects) <= 0.5
    assert facade_patch_bad_fraction(m, []) == 0.0


def test_texture_atlas_maps_each_face_to_its_colour():
    rng = np.random.default_rng(0)
    n = 3000
    m = Mesh(rng.random((3 * n, 3)), np.arange(3 * n).reshape(-1, 3), np.zeros(n, np.uint8), np.zeros(n, np.int32),
             rng.integers(0, 256, (n, 3)).astype(np.uint8))
    uv, atlases, idx = bake_atlas(m, rng, cell_px=8, max_side_px=256, noise_rgb=0.0, shade=0.0)
    assert uv.shape == (n, 3, 2) and uv.dtype == np.float32 and uv.min() > 0 and uv.max() < 1
    assert len(atlases) == 2 and all(a.shape[0] == a.shape[1] <= 256 and a.dtype == np.uint8 for a in atlases)
    assert np.array_equal(np.bincount(idx), [2048, 952])
    c = uv.mean(axis=1)
    for a, img in enumerate(atlases):
        s = idx == a
        H = img.shape[0]
        x, y = (c[s, 0] * H).astype(int), ((1 - c[s, 1]) * H).astype(int)
        assert np.array_equal(img[y, x], m.face_color[s])
