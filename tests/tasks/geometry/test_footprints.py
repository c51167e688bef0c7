"""Building footprints from a mesh (``tasks.geometry.footprints``): two box buildings and a car on a flat ground
grid, built in code; the buildings found with their areas and heights, the car not, facade points mapped to
their building, ids stable under a permutation of the faces, tiles merged as one."""

from __future__ import annotations

import numpy as np
import pytest

from tasks.geometry.footprints import CellHeights, cell_heights, footprints

# (x0, y0, x1, y1, height): two buildings 20 m apart, and a car-sized box
BIG = (10.0, 10.0, 20.0, 18.0, 12.0)
SMALL = (40.0, 12.0, 46.0, 18.0, 6.0)
CAR = (28.0, 25.0, 32.0, 27.0, 1.0)


def _box(x0, y0, x1, y1, h) -> np.ndarray:
    """(10, 3, 3) triangles: four walls from z 0 to ``h`` and a roof, two triangles each (no floor)."""
    c = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    tri = []
    for a, b in zip(c, np.roll(c, -1, axis=0)):
        lo_a, lo_b, hi_a, hi_b = [*a, 0.0], [*b, 0.0], [*a, h], [*b, h]
        tri += [[lo_a, lo_b, hi_b], [lo_a, hi_b, hi_a]]
    roof = [[*p, h] for p in c]
    tri += [[roof[0], roof[1], roof[2]], [roof[0], roof[2], roof[3]]]
    return np.array(tri, np.float64)


def _ground(boxes, size=(60.0, 40.0), step=2.0) -> np.ndarray:
    """Ground grid triangles at z 0, none whose centroid lies under a box (a photogrammetric mesh has no floor)."""
    xs, ys = np.arange(0.0, size[0], step), np.arange(0.0, size[1], step)
    x, y = (a.ravel() for a in np.meshgrid(xs, ys))
    p00, p10 = np.stack([x, y], 1), np.stack([x + step, y], 1)
    p11, p01 = np.stack([x + step, y + step], 1), np.stack([x, y + step], 1)
    tri = np.concatenate([np.stack([p00, p10, p11], 1), np.stack([p00, p11, p01], 1)])
    cen = tri.mean(1)
    under = np.zeros(len(tri), bool)
    for x0, y0, x1, y1, _ in boxes:
        under |= (cen[:, 0] > x0) & (cen[:, 0] < x1) & (cen[:, 1] > y0) & (cen[:, 1] < y1)
    tri = tri[~under]
    return np.concatenate([tri, np.zeros((*tri.shape[:2], 1))], axis=2)


def _scene() -> np.ndarray:
    boxes = [BIG, SMALL, CAR]
    return np.concatenate([_ground(boxes)] + [_box(*b) for b in boxes])


def test_two_boxes_are_two_buildings_with_their_area_and_height_and_the_car_is_none():
    fp = footprints(_scene())
    assert fp.n == 2
    assert fp.ids.tolist() == [1, 2]
    # ids by centroid (y, then x): the big box's centroid (15, 14) is south of the small one's (43, 15)
    big, small = 0, 1
    assert fp.centroid_xy[big] == pytest.approx((15.0, 14.0), abs=0.6)
    assert fp.centroid_xy[small] == pytest.approx((43.0, 15.0), abs=0.6)
    assert fp.area_m2[big] == pytest.approx(10 * 8, rel=0.15)
    assert fp.area_m2[small] == pytest.approx(6 * 6, rel=0.15)
    assert fp.height_m[big] == pytest.approx(12.0, abs=0.5)
    assert fp.height_m[small] == pytest.approx(6.0, abs=0.5)
    car = fp.building_of(np.array([[30.0, 26.0]]), pad_m=0.0)
    assert car.tolist() == [0]  # 1 m high: no building
    j = fp.to_json()
    assert [b["id"] for b in j["buildings"]] == [1, 2] and "labels" not in j


def test_points_at_and_beside_a_facade_map_to_its_building_and_the_street_to_none():
    fp = footprints(_scene())
    xy = np.array([
        [20.0, 14.0],  # on the big box's east facade
        [21.0, 14.0],  # 1 m outside it
        [15.0, 9.0],  # 1 m south of its south facade
        [39.0, 15.0],  # 1 m west of the small box's west facade
        [30.0, 14.0],  # the middle of the street between them
        [15.0, 30.0],  # open ground north of the big box
        [500.0, -300.0],  # far off the grid
    ])
    assert fp.building_of(xy).tolist() == [1, 1, 1, 2, 0, 0, 0]
    assert fp.building_of(xy, pad_m=0.0).tolist() == [1, 0, 0, 0, 0, 0, 0]  # no pad: only the footprint itself
    assert fp.building_of(np.zeros((0, 2))).shape == (0,)


def test_ids_are_stable_under_a_permutation_of_the_faces_and_a_split_into_tiles():
    tri = _scene()
    fp = footprints(tri)
    perm = np.random.default_rng(7).permutation(len(tri))
    again = footprints(tri[perm][:, [1, 2, 0]])  # faces shuffled, corners rotated
    np.testing.assert_array_equal(again.labels, fp.labels)
    np.testing.assert_array_equal(again.area_m2, fp.area_m2)
    # tile by tile (two halves of the shuffled faces), cells merged: the same buildings
    half = len(tri) // 2
    merged = CellHeights.merge([cell_heights(tri[perm][:half]), cell_heights(tri[perm][half:])])
    whole = cell_heights(tri)
    np.testing.assert_array_equal(merged.ij, whole.ij)
    np.testing.assert_array_equal(merged.zmax, whole.zmax)
    np.testing.assert_array_equal(merged.zmin, whole.zmin)


def test_a_roof_wider_than_the_ground_window_stays_one_whole_building():
    hall = (10.0, 10.0, 50.0, 50.0, 8.0)  # 40 x 40 m: the 25 m window cannot see past the middle of the roof
    fp = footprints(np.concatenate([_ground([hall], size=(60.0, 60.0)), _box(*hall)]))
    assert fp.n == 1
    assert fp.area_m2[0] == pytest.approx(40 * 40, rel=0.15)
    assert fp.building_of(np.array([[30.0, 30.0]])).tolist() == [1]


def test_thresholds_are_parameters():
    tri = _scene()
    assert footprints(tri, min_height_m=8.0).n == 1  # only the 12 m box
    assert footprints(tri, min_area_m2=60.0).n == 1  # only the 10 x 8 m box
    assert footprints(tri, min_height_m=0.5, min_area_m2=5.0).n == 3  # the car too
    assert footprints(np.zeros((0, 3, 3))).n == 0
