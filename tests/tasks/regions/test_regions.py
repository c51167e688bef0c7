"""Regions: 26-connected components of bad patches, growth, context, splitting, grades fallback."""

import numpy as np

from storage.grid import PatchGrid
from tasks.regions import connected_components, dilate, plan_regions

G = PatchGrid((2.3, 1.0, 0.7), tile_size_m=10.0)


def keys(*ijk):
    return PatchGrid.pack(np.array(ijk, np.int64))


def test_components_use_the_26_neighbourhood():
    k = keys([0, 0, 0], [1, 1, 1], [2, 2, 2], [4, 0, 0], [5, 0, 1], [9, 9, 9])
    lab = connected_components(k)
    assert lab.tolist() == [0, 0, 0, 1, 1, 2]
    assert connected_components(keys([0, 0, 0], [2, 0, 0])).tolist() == [0, 1]  # a gap of one cell splits


def test_dilate_and_plan_with_growth_and_context():
    allk = PatchGrid.pack(np.stack(np.meshgrid(range(6), range(6), range(2), indexing="ij"), -1).reshape(-1, 3))
    allk = np.sort(allk)
    assert len(dilate(keys([2, 2, 0]), 1, within=allk)) == 18
    bad = keys([1, 1, 0], [4, 4, 1])
    r0 = plan_regions(bad, allk, G, grow_cells=0, context_cells=1)
    assert len(r0) == 2 and all(r.n_patches == 1 for r in r0)
    assert len(r0[0].context) == 17  # 3 x 3 x 2 block minus itself
    far = keys([0, 0, 0], [5, 5, 1])
    r1 = plan_regions(far, allk, G, grow_cells=1, context_cells=1)
    assert len(r1) == 2 and sorted(r.n_patches for r in r1) == [8, 8]  # corners grown by one cell: still apart
    assert len(plan_regions(bad, allk, G, grow_cells=1)) == 1  # (1,1,0) and (4,4,1) grown: they touch
    assert plan_regions(bad, allk, G, min_patches=2) == []


def test_region_across_a_tile_corner_is_one_region():
    # cells either side of the tile corner at (10 m, 10 m): centres of i = 3 | 4 lie at x = 8.05 | 10.35,
    # of j = 9 | 10 at y = 9.5 | 10.5
    bad = keys([3, 9, 0], [4, 10, 0], [3, 10, 1], [4, 9, 1])
    r = plan_regions(bad, np.sort(bad), G)
    assert len(r) == 1 and sorted(r[0].tiles) == ["0_0", "0_1", "1_0", "1_1"]
    assert r[0].key == f"r{int(bad.min()):016x}"


def test_split_when_over_budget():
    row = np.sort(keys(*[[i, 0, 0] for i in range(40)]))
    r = plan_regions(row, row, G, patch_cost=np.full(40, 100.0), budget_bytes=1000.0)
    assert len(r) == 4 and sorted(x.n_patches for x in r) == [10, 10, 10, 10]
    assert len({x.parent for x in r}) == 1 and r[0].parent
    assert np.array_equal(np.sort(np.concatenate([x.patches for x in r])), row)  # a partition of the patches
