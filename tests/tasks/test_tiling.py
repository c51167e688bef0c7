import numpy as np

from storage.ids import TileId
from tasks.tiling import group_by_tile, tiles_for_bounds, transform_bounds


def test_tiles_for_bounds_covers_box():
    tiles = tiles_for_bounds(np.array([-5.0, 5, 0]), np.array([150.0, 20, 0]), 100)
    assert tiles == [TileId(-1, 0), TileId(0, 0), TileId(1, 0)]


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
