"""tasks.quality (metrics, tiled): measured accuracy of a mesh against the truth, on hand-built planes and boxes."""

import json
import math

import numpy as np
import pytest

from storage.errors import InputError
from storage.ids import TileId
from synth.scene import FaceClass
from tasks.geometry.distance import point_to_mesh_distance
from tasks.geometry.sampling import sample_surface, sample_weights
from tasks.quality.metrics import evaluate_mesh, facade_mask
from tasks.quality.tiled import evaluate_by_tile

NAMES = {c.value: c.name.lower() for c in FaceClass}


def plane(x0, y0, x1, y1, cell, z=0.0):
    """Grid of the rectangle [x0, x1] x [y0, y1] at height z: vertices (n, 3), faces (m, 3), 2 per cell."""
    xs, ys = np.arange(x0, x1 + 1e-9, cell), np.arange(y0, y1 + 1e-9, cell)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], 1)
    i, j = np.meshgrid(np.arange(len(xs) - 1), np.arange(len(ys) - 1), indexing="ij")
    a = (i * len(ys) + j).ravel()
    b, c = a + len(ys), a + len(ys) + 1
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, a + 1], 1)])
    return v, f


def box(lo, hi):
    """Closed axis-aligned box, 12 triangles, outward normals."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[(hi if (k >> d) & 1 else lo)[d] for d in range(3)] for k in range(8)])
    f = np.array([[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
                  [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]])
    return v, f


def join(*meshes):
    offs = np.cumsum([0] + [len(v) for v, _ in meshes[:-1]])
    return np.concatenate([v for v, _ in meshes]), np.concatenate([f + o for (_, f), o in zip(meshes, offs)])


def cut(v, f, lo, hi):
    """Remove the faces whose centroid lies in the x/y box [lo, hi]."""
    c = v[f].mean(1)[:, :2]
    return v, f[~((c >= lo) & (c <= hi)).all(1)]


def test_point_to_mesh_distance_exact_in_every_voronoi_region():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    f = np.array([[0, 1, 2]])
    p = np.array([[0.2, 0.2, 0.5], [-1, -1, 0], [2, 0, 0], [0.5, -2, 0], [1, 1, 0], [-3, 0.5, 4]])
    want = [0.5, math.sqrt(2), 1.0, 2.0, math.sqrt(0.5), 5.0]
    d, fid = point_to_mesh_distance(p, v, f, return_faces=True)
    np.testing.assert_allclose(d, want, rtol=0, atol=1e-12)
    assert fid.tolist() == [0] * 6
    far = np.array([512345.678, 5412345.678, 91.0])
    d_world = point_to_mesh_distance(p + far, v + far, f)
    np.testing.assert_allclose(d_world, want, rtol=0, atol=1e-8)
    assert np.isinf(point_to_mesh_distance(p, np.zeros((0, 3)), np.zeros((0, 3), np.int64))).all()


def test_sampling_is_area_weighted_stratified_and_deterministic():
    v, f = join(plane(0, 0, 10, 10, 2.5), box((20, 0, 0), (20.3, 0.3, 0.3)))  # big and tiny faces
    p, fid = sample_surface(v, f, spacing_m=0.1, rng=7)
    p2, fid2 = sample_surface(v, f, spacing_m=0.1, rng=7)
    assert np.array_equal(p, p2) and np.array_equal(fid, fid2)
    assert not np.array_equal(p, sample_surface(v, f, spacing_m=0.1, rng=8)[0])
    g1, g2 = (sample_surface(v, f, 0.1, rng=np.random.default_rng(5))[0] for _ in range(2))
    assert np.array_equal(g1, g2)
    w = sample_weights(v, f, fid, spacing_m=0.1)
    assert w.sum() == pytest.approx(100 + 6 * 0.09, rel=1e-12)
    assert np.bincount(fid, minlength=len(f))[:len(f) - 12].tolist() == [312] * (len(f) - 12)  # 3.125 m² each
    flat = p[fid < len(f) - 12]
    counts = np.histogram2d(flat[:, 0], flat[:, 1], bins=10, range=[[0, 10], [0, 10]])[0]
    assert counts.min() >= 90 and counts.max() <= 110  # iid sampling would spread ~ +-30
    sub = np.arange(0, len(f), 3)  # a face's samples do not depend on the other faces
    ps, fs = sample_surface(v, f[sub], spacing_m=0.1, rng=7)
    assert np.array_equal(ps, p[np.isin(fid, sub)]) and np.array_equal(sub[fs], fid[np.isin(fid, sub)])


def test_identical_meshes_measure_zero():
    mesh = join(plane(0, 0, 12, 12, 1.0), box((3, 3, 0), (9, 8, 6)))
    r = evaluate_mesh(*mesh, *mesh, spacing_m=0.05)
    assert r.accuracy.max_m < 1e-9 and r.completeness.max_m < 1e-9 and r.chamfer_m < 1e-9
    assert r.fscore == (1.0, 1.0) and r.precision == (1.0, 1.0) and r.recall == (1.0, 1.0)
    assert r.uncovered_area_m2 == 0.0 and r.far_area_m2 == 0.0
    assert r.completeness.area_m2 == pytest.approx(144 + 2 * (6 * 5 + 6 * 6 + 5 * 6), rel=1e-9)


@pytest.mark.parametrize("tilted", [False, True])
def test_shift_along_normal_measures_the_shift(tilted):
    v, f = plane(0, 0, 8, 8, 0.5)
    normal = np.array([0.0, 0.0, 1.0])
    if tilted:  # any orientation, e.g. a facade leaning out
        a, b = 0.7, 0.4
        rot = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]]) @ \
            np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
        v, normal = v @ rot.T, rot @ normal
    r = evaluate_mesh(v + 0.03 * normal, f, v, f, taus=(0.02, 0.05), spacing_m=0.04)
    for s in (r.accuracy, r.completeness):
        assert s.mean_m == pytest.approx(0.03, abs=0.002)
        assert s.median_m == pytest.approx(0.03, abs=0.002) and s.rms_m == pytest.approx(0.03, abs=0.002)
    assert r.fscore[1] == 1.0 and r.fscore[0] < 0.01
    assert r.chamfer_l2_m2 == pytest.approx(0.03**2, rel=0.05)


def test_hole_is_measured_as_uncovered_area_and_lowers_recall():
    truth = plane(0, 0, 10, 10, 0.5)
    pred = cut(*truth, (4.0, 4.0), (5.0, 5.0))  # 1 m x 1 m hole, 8 triangles
    assert len(truth[1]) - len(pred[1]) == 8
    r = evaluate_mesh(*pred, *truth, spacing_m=0.03)
    assert r.uncovered_area_m2 == pytest.approx(1.0, rel=0.10)
    assert r.uncovered_fraction == pytest.approx(0.01, rel=0.10)
    assert r.far_area_m2 == pytest.approx((1 - 2 * 0.2) ** 2, rel=0.10)  # eroded by the 0.20 m threshold
    assert r.precision == (1.0, 1.0)
    # truth within 5 cm (10 cm) of the rim is recalled
    assert r.recall[0] == pytest.approx(1 - (1 - 2 * 0.05) ** 2 / 100, abs=0.001)
    assert r.recall[1] == pytest.approx(1 - (1 - 2 * 0.10) ** 2 / 100, abs=0.001)
    centroids = truth[0][truth[1]].mean(1)
    away = centroids[:, 0] > 6  # a facade mask that excludes the hole
    r2 = evaluate_mesh(*pred, *truth, spacing_m=0.03, true_face_mask=away, chunk_size=9973)
    assert r2.uncovered_area_m2 == 0.0 and r2.evaluated_area_m2 == pytest.approx(40.0, rel=1e-9)
    assert r2.recall == pytest.approx(r.recall, abs=1e-12)  # chunking changes nothing
    assert r2.completeness.max_m == r.completeness.max_m and r2.accuracy.n_samples == r.accuracy.n_samples


def test_extra_blob_lowers_precision_not_recall():
    truth = plane(0, 0, 10, 10, 1.0)
    pred = join(truth, box((4, 4, 2), (5, 5, 3)))  # 6 m² floating 2 m above the ground
    r = evaluate_mesh(*pred, *truth, spacing_m=0.05)
    assert r.recall == (1.0, 1.0) and r.uncovered_area_m2 == 0.0
    assert r.precision[0] == pytest.approx(100 / 106, abs=1e-9)
    assert r.accuracy.max_m == pytest.approx(3.0, abs=0.05) and r.completeness.max_m < 1e-9


def test_per_class_figures_and_facade_mask():
    ground = plane(0, 0, 10, 10, 1.0)
    wall_t = np.array([[2, 6, 0], [8, 6, 0], [8, 6, 3], [2, 6, 3]], float), np.array([[0, 1, 2], [0, 2, 3]])
    truth = join(ground, wall_t)
    cls = np.r_[np.full(len(ground[1]), FaceClass.GROUND), np.full(2, FaceClass.WALL)]
    pred = join(ground, (wall_t[0] + [0, 0.08, 0], wall_t[1]))  # the wall is 8 cm off
    r = evaluate_mesh(*pred, *truth, spacing_m=0.05, true_face_class=cls, class_names=NAMES,
                      true_face_mask=facade_mask(cls))
    assert set(r.per_class) == {"ground", "wall"}
    wall = r.per_class["wall"]
    assert wall.completeness.area_m2 == pytest.approx(18.0, rel=1e-9)
    assert wall.completeness.median_m == pytest.approx(0.08, abs=0.001)
    assert wall.recall[0] == pytest.approx(0.05 / 3, abs=0.002)  # only its foot, within 5 cm of the ground
    assert wall.recall[1] == 1.0
    assert r.per_class["ground"].completeness.p95_m < 1e-6 and r.per_class["ground"].recall == (1.0, 1.0)
    assert r.evaluated_area_m2 == pytest.approx(18.0, rel=1e-9) and r.uncovered_area_m2 == 0.0
    json.dumps(r.to_dict(), allow_nan=False)
    assert "wall" in str(r) and "completeness" in str(r)


def _scene_across_two_tiles():
    truth = join(plane(0, 0, 19.6, 9.8, 0.7), box((12, 2, 0), (15, 6, 4)))  # cells straddle x = 10
    pred = join(plane(0, 0, 19.6, 9.8, 0.7, z=0.02), box((12, 2, 0.0), (15, 6, 4.02)))
    pred = cut(*pred, (9.0, 3.0), (10.6, 4.5))  # a hole across the tile border
    pred = join(pred, box((4, 4, 1), (5, 5, 2)))  # an extra blob in tile (0, 0)
    cls = np.r_[np.full(len(truth[1]) - 12, FaceClass.GROUND), np.full(12, FaceClass.WALL)]
    return pred, truth, cls


def test_by_tile_aggregates_exactly_to_the_global_result():
    pred, truth, cls = _scene_across_two_tiles()
    kw = {"spacing_m": 0.06, "true_face_class": cls, "class_names": NAMES, "rng": 3}
    tiled = evaluate_by_tile(*pred, *truth, tile_size_m=10.0, buffer_m=1.5, **kw)
    whole = evaluate_mesh(*pred, *truth, max_distance_m=1.5, **kw)
    assert sorted(tiled.tiles) == [TileId(0, 0), TileId(1, 0)]
    a, b = tiled.total, whole
    for sa, sb in ((a.accuracy, b.accuracy), (a.completeness, b.completeness)):
        assert sa.n_samples == sb.n_samples
        for k in ("area_m2", "mean_m", "median_m", "p90_m", "p95_m", "rms_m", "max_m"):
            assert getattr(sa, k) == pytest.approx(getattr(sb, k), rel=1e-9, abs=1e-12), k
    assert a.fscore == pytest.approx(b.fscore, abs=1e-12) and a.recall == pytest.approx(b.recall, abs=1e-12)
    assert a.uncovered_area_m2 == pytest.approx(b.uncovered_area_m2, rel=1e-9)
    assert a.uncovered_area_m2 == pytest.approx(10 * 0.245, rel=0.05)  # the 10 triangles cut
    wall_a, wall_b = a.per_class["wall"].completeness, b.per_class["wall"].completeness
    assert wall_a.mean_m == pytest.approx(wall_b.mean_m, rel=1e-9) and wall_a.area_m2 == pytest.approx(80.0)
    n_tiles = sum(t.completeness.n_samples for t in tiled.tiles.values())
    assert n_tiles == whole.completeness.n_samples
    assert tiled.tiles[TileId(0, 0)].precision[0] < 0.97 < tiled.tiles[TileId(1, 0)].precision[0]


def test_world_coordinates_give_the_local_result():
    pred, truth, cls = _scene_across_two_tiles()
    shift = np.array([500_000.0, 5_000_000.0, 100.0])
    local = evaluate_mesh(*pred, *truth, spacing_m=0.06, true_face_class=cls, class_names=NAMES)
    world = evaluate_mesh(pred[0] + shift, pred[1], truth[0] + shift, truth[1], spacing_m=0.06,
                          true_face_class=cls, class_names=NAMES)
    assert world.accuracy.n_samples == local.accuracy.n_samples
    assert world.completeness.n_samples == local.completeness.n_samples
    for k in ("mean_m", "rms_m", "median_m", "p95_m", "max_m"):
        assert getattr(world.accuracy, k) == pytest.approx(getattr(local.accuracy, k), abs=1e-6), k
        assert getattr(world.completeness, k) == pytest.approx(getattr(local.completeness, k), abs=1e-6), k
    assert world.fscore == pytest.approx(local.fscore, abs=1e-9)
    assert world.uncovered_area_m2 == pytest.approx(local.uncovered_area_m2, rel=1e-6)


def test_empty_prediction_and_bad_input():
    truth = plane(0, 0, 4, 4, 1.0)
    r = evaluate_mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), *truth, spacing_m=0.1)
    assert r.recall == (0.0, 0.0) and r.uncovered_fraction == 1.0 and math.isinf(r.completeness.mean_m)
    assert math.isnan(r.accuracy.mean_m) and r.accuracy.n_samples == 0
    d = r.to_dict()
    json.dumps(d, allow_nan=False)
    assert d["completeness"]["mean_m"] is None
    bad = truth[0].copy()
    bad[3, 2] = np.nan
    with pytest.raises(InputError, match="NaN"):
        evaluate_mesh(bad, truth[1], *truth)
    with pytest.raises(InputError, match="face indices"):
        evaluate_mesh(truth[0], truth[1] + 100, *truth)
