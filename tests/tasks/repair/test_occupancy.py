"""A tile's MLS occupancy (the texture step's occluders) built window by window equals the voxels of all its
points at once, so its memory no longer grows with the scan's density."""

from __future__ import annotations

import numpy as np

from storage.patches.read import PatchStore
from tasks.repair import texture_inputs
from tasks.repair.texture_inputs import occupancy, voxel_cells


def test_occupancy_in_windows_equals_all_points_at_once(tiny_work, tmp_path, monkeypatch):
    _, wd = tiny_work
    tile = max((wd.tile_dir(t) for t in wd.live_tiles()), key=lambda d: PatchStore(d).n_points)
    store = PatchStore(tile)
    pts, _ = store.read_all(point_columns=["x", "y", "z"], face_columns=["patch"])
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1)
    want = ((np.unique(np.floor(xyz / 0.2).astype(np.int64), axis=0) + 0.5) * 0.2).astype(np.float32)
    monkeypatch.setattr(texture_inputs, "OCCUPANCY_WINDOW", store.n_points // 9 + 1)
    got = occupancy(tile, tmp_path / "occ.npz", 0.2)
    assert len(want) > 1000
    np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(occupancy(tile, tmp_path / "occ.npz", 0.2), want)  # from the cache


def test_voxel_cells_sorts_like_unique_rows_with_and_without_packing():
    rng = np.random.default_rng(0)
    for span in (50, 3_000_000):  # within +-2^20: packed keys; beyond: rows
        cells = rng.integers(-span, span, (5_000, 3))
        cells[::7] = cells[1::7][: len(cells[::7])]
        np.testing.assert_array_equal(voxel_cells(cells), np.unique(cells, axis=0))
