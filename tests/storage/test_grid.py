"""The world-anchored patch grid: ids do not depend on the campus origin."""

import numpy as np
import pytest

from storage.grid import BITS, GridRangeError, PatchGrid

SIZE = (2.3, 1.0, 0.7)


def test_cells_are_world_anchored():
    g = PatchGrid(SIZE, 100.0)
    world = np.array([[589_001.0, 2_712_000.5, 14.2], [589_100.0, 2_712_050.0, -3.0]])
    ijk = g.cells_world(world)
    assert ijk.tolist() == [[256087, 2712000, 20], [256130, 2712050, -5]]
    for origin in ([589_000.0, 2_712_000.0, 0.0], [588_000.0, 2_711_000.0, 0.0], [0.0, 0.0, 0.0]):
        local = (world - origin).astype(np.float32)
        assert g.cells_local(local, origin).tolist() == ijk.tolist()


def test_tiles_and_bounds():
    g = PatchGrid(SIZE, 100.0)
    ijk = np.array([[256087, 2712000, 20]])
    assert g.tile_of_cells(ijk).tolist() == [[5890, 27120]]
    assert g.tile_of_keys(g.pack(ijk)).tolist() == [[5890, 27120]]
    lo, hi = g.bounds_local(ijk, (589_000.0, 2_712_000.0, 0.0))
    assert np.allclose(lo, [[256087 * 2.3 - 589_000, 0.0, 14.0]]) and np.allclose(hi - lo, [SIZE])
    assert np.allclose(g.centre_world(ijk), lo + np.array(SIZE) / 2 + [589_000.0, 2_712_000.0, 0.0])


def test_anchor_shifts_the_grid():
    g = PatchGrid(SIZE, 100.0, anchor_m=(1000.0, 0.0, 0.0))
    assert g.cells_world(np.array([[1000.1, 0.5, 0.1]])).tolist() == [[0, 0, 0]]
    assert g.tile_of_cells(np.array([[0, 0, 0]])).tolist() == [[0, 0]]


def test_pack_range_and_order():
    half = [1 << (b - 1) for b in BITS]
    ijk = np.array([[-half[0], -half[1], -half[2]], [half[0] - 1, half[1] - 1, half[2] - 1], [0, 0, 0]])
    keys = PatchGrid.pack(ijk)
    assert (keys >= 0).all() and np.array_equal(PatchGrid.unpack(keys), ijk)
    assert keys[0] < keys[2] < keys[1]
    with pytest.raises(GridRangeError):
        PatchGrid.pack(np.array([[half[0], 0, 0]]))


def test_clear_errors():
    g = PatchGrid(SIZE, 100.0)
    with pytest.raises(GridRangeError, match="NaN"):
        g.cells_world(np.array([[np.nan, 0.0, 0.0]]))
    with pytest.raises(GridRangeError, match="anchor"):
        PatchGrid((0.023, 0.01, 0.007)).cells_world(np.array([[589_000.0, 2_712_000.0, 0.0]]))
    with pytest.raises(ValueError):
        PatchGrid((0.0, 1.0, 1.0))
