import numpy as np

from storage.grid import PatchGrid
from tasks.geometry.tiling import group_by_tile, transform_bounds


def test_tiles_for_bounds_covers_box():
    grid = PatchGrid((2.3, 1.0, 0.7), 100.0)
    tiles = grid.tiles_for_bounds(np.array([-5.0, 5, 0]), np.array([150.0, 20, 0]))
    assert tiles.tolist() == [[-1, 0], [0, 0], [1, 0]]
    world = grid.tiles_for_bounds(np.array([589_001.0, 2_712_099.5, 0]), np.array([589_002.0, 2_712_100.5, 0]))
    assert world.tolist() == [[5890, 27120], [5890, 27121]]


def test_group_by_tile_partitions_rows():
    rng = np.random.default_rng(0)
    tij = rng.integers(-3, 3, size=(1000, 2))
    groups = group_by_tile(tij)
    idx = np.concatenate([g for _, g in groups])
    assert np.array_equal(np.sort(idx), np.arange(1000))  # every row exactly once
    for tile, g in groups:
        assert (tij[g] == [tile.ix, tile.iy]).all()
    assert [t for t, _ in groups] == sorted(t for t, _ in groups)


def test_transform_bounds_rotation():
    m = np.eye(4)
    m[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]  # 90 deg about z
    lo, hi = transform_bounds(m, np.array([0.0, 0, 0]), np.array([2.0, 1, 1]))
    assert np.allclose(lo, [-1, 0, 0]) and np.allclose(hi, [0, 2, 1])
