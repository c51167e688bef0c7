"""The merge's keys of a rebuilt region's own vertices lie in their own block of the vertex-id namespace
(``storage.vertex_ids``, block ``merge_own``): never a campus id, never a split vertex's hashed id, distinct
per region of the merge."""

import numpy as np

from storage.contracts.region_mesh import RegionMesh
from storage.vertex_ids import BLOCKS, SPLIT_MIN, is_campus_id, local_ids
from tasks.geometry.split import split_vertex_id
from tasks.merge.soup import region_soup


def _region(number: int, ids: np.ndarray | None) -> RegionMesh:
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], np.float32)
    return RegionMesh(number, v, np.array([[0, 1, 2], [1, 3, 2]]), vertex_ids=ids)


def test_own_vertices_take_keys_of_the_merge_block_and_campus_vertices_their_ids():
    split = split_vertex_id(np.array([5]), np.array([9]))[0]
    old_style = -1 - ((np.int64(7) << 32) | 1)  # what vertex 1 of region 7 was keyed before: inside SPLIT range
    assert SPLIT_MIN <= old_style <= -2
    ids = np.array([(3 << 32) | 4, -1, local_ids(np.arange(1), "rebuilt")[0], split], np.int64)
    keys = np.concatenate([region_soup(_region(7, ids), -1, rank).keys.ravel() for rank in (0, 1)])
    campus = is_campus_id(keys)
    assert set(keys[campus].tolist()) == {(3 << 32) | 4, int(split)}
    own = keys[~campus]
    lo, hi = local_ids(np.array([(1 << 58) - 1]), "merge_own")[0], local_ids(np.zeros(1), "merge_own")[0]
    assert ((own >= lo) & (own <= hi)).all() and old_style not in own
    assert len(np.unique(own)) == 4  # two own vertices per region, two regions (ranks): all distinct
    assert BLOCKS["merge_own"] not in {BLOCKS[k] for k in BLOCKS if k != "merge_own"}


def test_a_region_without_ids_is_all_own_keys():
    keys = region_soup(_region(1 << 30, None), -1, 3).keys
    assert not is_campus_id(keys).any()
