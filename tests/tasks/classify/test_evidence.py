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
