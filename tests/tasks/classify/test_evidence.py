"""The geometric evidence rule (tasks.classify.evidence) on hand-made walls and points."""

from __future__ import annotations

import numpy as np

from storage.grid import PatchGrid
from tasks.classify.evidence import offset_evidence, range_rows

SIZE = (2.3, 1.0, 0.7)


def _wall(x0=0.0, x1=6.9, y=0.5, z0=0.0, z1=2.8, step=0.7) -> np.ndarray:
    """A wall in the plane y = ``y``, cut into triangles small enough to sit one patch each: (m, 3, 3)."""
    xs, zs = np.arange(x0, x1 + 1e-9, step / 2), np.arange(z0, z1 + 1e-9, step / 2)
    tris = []
    for a, b in zip(xs[:-1], xs[1:]):
        for c, d in zip(zs[:-1], zs[1:]):
            tris += [[[a, y, c], [b, y, c], [b, y, d]], [[a, y, c], [b, y, d], [a, y, d]]]
    return np.array(tris, float)


def _grid_points(x0, x1, y, z0, z1, n=12) -> np.ndarray:
    g = np.stack(np.meshgrid(np.linspace(x0, x1, n), np.linspace(z0, z1, n), indexing="ij"), -1).reshape(-1, 2)
    return np.stack([g[:, 0], np.full(len(g), y), g[:, 1]], 1)


def _evidence(points: np.ndarray, tris: np.ndarray, **kw):
    """Bin points and faces (by centroid) into the patch grid and run the rule: (evidence, cells of the patches)."""
    grid = PatchGrid(SIZE)
    pc, fc = grid.cells_world(points), grid.cells_world(tris.mean(axis=1))
    cells, inv = np.unique(np.concatenate([pc, fc]), axis=0, return_inverse=True)
    inv = inv.ravel()
    prow, frow = inv[:len(points)], inv[len(points):]
    o = np.argsort(prow, kind="stable")
    verts, faces = tris.reshape(-1, 3), np.arange(3 * len(tris)).reshape(-1, 3)
    return offset_evidence(points[o], prow[o], verts, faces, frow, cells, **kw), cells


def _verdict(ev, cells, point):
    """(bad, offset_m) of the patch holding ``point``."""
    c = PatchGrid(SIZE).cells_world(np.array([point]))[0]
    r = np.flatnonzero((cells == c).all(axis=1))[0]
    return bool(ev.bad[r]), float(ev.offset_m[r])


def test_points_on_the_wall_are_good_behind_it_bad():
    wall = _wall()  # patch row j = 0 (y in [0, 1)), the wall at y = 0.5
    rng = np.random.default_rng(0)
    on = _grid_points(0.1, 2.2, 0.5, 0.05, 0.65) + rng.normal(0, 0.01, (144, 3)) * [0, 1, 0]
    behind = _grid_points(2.4, 4.5, 0.9, 0.05, 0.65)  # a recess 0.4 m behind the modelled wall, same patch row
    ev, cells = _evidence(np.concatenate([on, behind]), wall)
    bad, off = _verdict(ev, cells, on[0])
    assert not bad and off < 0.05
    bad, off = _verdict(ev, cells, behind[0])
    assert bad and abs(off - 0.4) < 1e-3
    assert not ev.missing.any()


def test_points_without_faces_next_to_the_wall_are_bad_far_away_unknown():
    wall = _wall(y=0.2)  # faces in the row j = 0; points in j = -1 (a balcony 0.7 m in front) have none
    balcony = _grid_points(0.1, 2.2, -0.5, 0.75, 1.35)
    lone = _grid_points(30.1, 32.2, -0.5, 0.75, 1.35)  # a points-only patch far from any face (a tree)
    ev, cells = _evidence(np.concatenate([balcony, lone]), wall)
    bad, off = _verdict(ev, cells, balcony[0])
    assert bad and abs(off - 0.7) < 1e-3
    r = np.flatnonzero((cells == PatchGrid(SIZE).cells_world(balcony[:1])[0]).all(axis=1))[0]
    assert ev.missing[r]
    bad, off = _verdict(ev, cells, lone[0])
    assert not bad and np.isinf(off)
    # too few points: no evidence either way
    ev, cells = _evidence(balcony[:4], wall)
    assert not ev.bad.any() and np.isnan(_verdict(ev, cells, balcony[0])[1])


def test_things_standing_on_the_ground_do_not_count():
    ground = _wall(y=0.0)[:, :, [0, 2, 1]]  # the same triangles laid flat: z = 0
    car = np.array([[x, y, 0.9] for x in np.linspace(0.2, 2.0, 8) for y in np.linspace(0.1, 0.9, 8)])
    ev, cells = _evidence(car, ground)
    assert not ev.bad.any()
    ev, _ = _evidence(car, ground, standing_normal_z=1.0)  # counted, they would be bad
    assert ev.bad.any()


def test_range_rows():
    assert range_rows(np.array([0, 2, 2]), np.array([2, 2, 5]), 6).tolist() == [0, 0, 2, 2, 2, -1]


def test_points_inside_a_closed_block_are_bad_outside_unknown():
    """A passage through a city model's solid block: points deep inside it (farther from every face than
    evidence_near_m) are graded bad; the same points outside a block stay unknown."""
    import trimesh

    block = trimesh.creation.box(extents=(20.0, 12.0, 9.0))
    block.apply_translation((10.0, 6.0, 4.5))
    tris = np.asarray(block.triangles, float)
    passage = _grid_points(8.1, 10.2, 6.0, 0.3, 2.6)  # a wall of the passage 6 m inside the block
    outside = passage + [0.0, 20.0, 0.0]
    ev, cells = _evidence(np.concatenate([passage, outside]), tris)
    bad, off = _verdict(ev, cells, passage[0])
    assert bad
    assert not _verdict(ev, cells, outside[0])[0]
    r = np.flatnonzero((cells == PatchGrid(SIZE).cells_world(passage[:1])[0]).all(axis=1))[0]
    assert ev.missing[r]
    ev, cells = _evidence(np.concatenate([passage, outside]), tris, inside_share=2.0)  # rule off
    assert not _verdict(ev, cells, passage[0])[0]


def test_sampling_from_row_ranges_picks_the_points_the_rule_picks_itself():
    """tile_evidence samples from the patches' row ranges (no per-point array): the same points, in the
    same order, as offset_evidence's own striding over a per-point row array."""
    from tasks.classify.evidence import _strided_rows, strided_ranges

    rng = np.random.default_rng(3)
    count = rng.integers(0, 900, 50)
    count[::7] = 0  # patches without points
    start = np.r_[0, np.cumsum(count)[:-1]]
    idx, row = strided_ranges(start, start + count, 200)
    point_row = np.repeat(np.arange(len(count)), count)
    assert np.array_equal(idx, _strided_rows(point_row, 200)) and np.array_equal(row, point_row[idx])
    assert np.bincount(row, minlength=len(count)).max() <= 200 and len(idx) < count.sum()


def test_a_welded_mesh_gives_the_soups_evidence_and_ids_that_disagree_keep_the_soup():
    from tasks.classify.evidence import weld_by_ids

    wall = _wall().astype(np.float32).astype(np.float64)  # positions as a store holds them (float32)
    corners = wall.reshape(-1, 3)
    _, vids = np.unique(corners, axis=0, return_inverse=True)  # one id per position: a welded mesh
    v, f = weld_by_ids(wall.astype(np.float32), vids.reshape(-1, 3))
    assert len(v) < len(corners) / 4 and np.array_equal(v[f], wall)
    rng = np.random.default_rng(0)
    pts = np.concatenate([_grid_points(0.1, 2.2, 0.5, 0.05, 0.65) + rng.normal(0, 0.01, (144, 3)) * [0, 1, 0],
                          _grid_points(2.4, 4.5, 0.9, 0.05, 0.65)])
    grid = PatchGrid(SIZE)
    pc, fc = grid.cells_world(pts), grid.cells_world(wall.mean(axis=1))
    cells, inv = np.unique(np.concatenate([pc, fc]), axis=0, return_inverse=True)
    prow, frow = inv.ravel()[:len(pts)], inv.ravel()[len(pts):]
    o = np.argsort(prow, kind="stable")
    soup = offset_evidence(pts[o], prow[o], corners, np.arange(len(corners)).reshape(-1, 3), frow, cells)
    welded = offset_evidence(pts[o], prow[o], v, f, frow, cells)
    assert np.array_equal(soup.offset_m, welded.offset_m, equal_nan=True) and np.array_equal(soup.bad, welded.bad)
    assert soup.bad.any()
    bad_ids = vids.reshape(-1, 3).copy()
    bad_ids[0, 0] = bad_ids[5, 2] if (corners[bad_ids[5, 2]] != corners[0]).any() else bad_ids[7, 1]
    v2, f2 = weld_by_ids(wall.astype(np.float32), bad_ids)  # one id now names two positions
    assert len(v2) == len(corners) and np.array_equal(v2[f2], wall)
