import numpy as np
import pytest

from tasks.partition import (
    BIAS,
    Partition,
    build_tile_tables,
    face_patches,
    merge_pair_index,
    pack_patch_key,
    partition_cells,
    partition_faces,
    partition_points,
    patch_centre,
    patch_index,
    tile_of_faces,
    tile_of_patch,
    tile_of_points,
    unpack_patch_key,
    vertex_patches,
)

SIZE = (2.3, 1.0, 0.7)


def _check_partition(part: Partition, ijk_rows: np.ndarray):
    n = len(ijk_rows)
    assert part.order.dtype == np.int64 and sorted(part.order.tolist()) == list(range(n))  # a permutation
    assert part.counts.sum() == n and (part.counts > 0).all()
    assert part.starts[0] == 0 and part.stops[-1] == n
    assert np.array_equal(part.starts[1:], part.stops[:-1])  # ranges tile 0:n in order
    assert (np.diff(part.keys) > 0).all()
    sorted_keys = pack_patch_key(ijk_rows[part.order])
    assert np.array_equal(sorted_keys, np.repeat(part.keys, part.counts))  # every row in its range's patch
    assert np.array_equal(part.sorted_keys(), sorted_keys)
    # stable: inside a patch, rows keep their input order
    for s, e in zip(part.starts[:20], part.stops[:20]):
        assert (np.diff(part.order[s:e]) > 0).all()


def test_patch_index_by_hand():
    pts = np.array([[5.0, 2.5, 1.0], [-0.1, -0.1, -0.1], [0.0, 0.0, 0.0], [2.3, 1.0, 0.7]], dtype=np.float32)
    ijk = patch_index(pts, SIZE)
    assert ijk.dtype == np.int32
    assert ijk[:2].tolist() == [[2, 2, 1], [-1, -1, -1]]
    assert ijk[2].tolist() == [0, 0, 0]
    # float32(2.3) = 2.2999999523..., float32(0.7) = 0.69999998..: just below the boundary, computed in float64
    assert ijk[3].tolist() == [0, 1, 0]
    assert vertex_patches(pts, SIZE).tolist() == ijk.tolist()


def test_patch_index_rejects_nan_and_far():
    with pytest.raises(ValueError):
        patch_index(np.array([[np.nan, 0, 0]]), SIZE)
    with pytest.raises(ValueError):
        patch_index(np.array([[0, 2.0**21, 0]]), SIZE)


def test_pack_unpack_round_trip():
    rng = np.random.default_rng(1)
    ijk = rng.integers(-BIAS, BIAS, size=(10_000, 3)).astype(np.int32)
    ijk[:3] = [[-BIAS, -BIAS, -BIAS], [BIAS - 1, BIAS - 1, BIAS - 1], [0, -1, 1]]
    keys = pack_patch_key(ijk)
    assert keys.dtype == np.int64 and (keys >= 0).all()
    assert np.array_equal(unpack_patch_key(keys), ijk)
    assert len(np.unique(keys)) == len(np.unique(ijk, axis=0))
    # ascending keys == lexicographic (i, j, k)
    lex = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
    assert (np.diff(keys[lex]) >= 0).all()
    with pytest.raises(ValueError):
        pack_patch_key(np.array([[BIAS, 0, 0]]))


def test_partition_points_conserves_and_groups():
    rng = np.random.default_rng(2)
    xyz = (rng.random((20_000, 3)) * [30, 20, 10] - [10, 5, 3]).astype(np.float32)
    part = partition_points(xyz, SIZE)
    _check_partition(part, patch_index(xyz, SIZE))
    assert np.array_equal(part.ijk, unpack_patch_key(part.keys))


def test_partition_fallback_path_matches():
    """Cells spread so wide that rank + row bits exceed 63: the stable-argsort path gives the same answer."""
    ijk = np.array([[-BIAS, 0, 5], [BIAS - 1, BIAS - 1, -BIAS], [0, 0, 0], [-BIAS, 0, 5], [0, 0, 0]], dtype=np.int32)
    part = partition_cells(ijk)
    _check_partition(part, ijk)
    assert part.order.tolist() == [0, 3, 2, 4, 1]
    assert part.counts.tolist() == [2, 2, 1]


def test_partition_faces_by_centroid():
    # one triangle whose vertices lie in three patches, centroid (1.0, 0.5, 0.3) in patch (0, 0, 0)
    tri = np.array([[[0.1, 0.1, 0.1], [2.5, 0.2, 0.1], [0.4, 1.2, 0.75]],
                    [[-1.0, -1.0, -1.0], [-1.1, -1.0, -1.0], [-1.0, -1.1, -1.0]]], dtype=np.float32)
    assert face_patches(tri, SIZE).tolist() == [[0, 0, 0], [-1, -2, -2]]
    assert vertex_patches(tri[0], SIZE).tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 1]]
    rng = np.random.default_rng(3)
    tris = (rng.random((5000, 1, 3)) * [20, 20, 5] + rng.normal(0, 0.3, (5000, 3, 3))).astype(np.float32)
    part = partition_faces(tris, SIZE)
    _check_partition(part, face_patches(tris, SIZE))


def test_empty_partition():
    part = partition_points(np.zeros((0, 3), np.float32), SIZE)
    assert part.n_rows == 0 and len(part.keys) == 0


def test_tile_of_patch_uses_centre():
    # patch i = 43 spans x in [98.9, 101.2): straddles the 100 m border, centre 100.05 -> tile 1
    ijk = np.array([[43, 0, 0], [42, 0, 0], [-1, -1, 0], [0, 99, 3]])
    assert tile_of_patch(ijk, SIZE, 100.0).tolist() == [[1, 0], [0, 0], [-1, -1], [0, 0]]
    assert np.allclose(patch_centre(ijk[:1], SIZE), [[100.05, 0.5, 0.35]])
    # a point at x = 99.5 lies in patch 43, hence in tile 1 although x < 100
    assert tile_of_points(np.array([[99.5, 10.0, 0.0]]), SIZE, 100.0).tolist() == [[1, 0]]
    tri = np.array([[[99.2, 1, 0], [99.4, 1, 0], [99.3, 1.2, 0]]])
    assert tile_of_faces(tri, SIZE, 100.0).tolist() == [[1, 0]]


def test_merge_pair_index_union_with_empty_ranges():
    pts = np.array([[0.5, 0.5, 0.2], [0.6, 0.5, 0.2], [5.0, 0.5, 0.2]], np.float32)  # patches (0,0,0), (2,0,0)
    tris = np.array([[[0.1, 0.1, 0.1]] * 3, [[3.0, 0.1, 0.1]] * 3], np.float32)        # (0,0,0), (1,0,0)
    keys, pr, fr = merge_pair_index(partition_points(pts, SIZE), partition_faces(tris, SIZE))
    assert unpack_patch_key(keys).tolist() == [[0, 0, 0], [1, 0, 0], [2, 0, 0]]
    assert pr.tolist() == [[0, 2], [2, 2], [2, 3]]
    assert fr.tolist() == [[0, 1], [1, 2], [2, 2]]


def test_build_tile_tables():
    rng = np.random.default_rng(4)
    n, m = 3000, 400
    xyz = (rng.random((n, 3)) * [10, 6, 4]).astype(np.float32)
    pc = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "intensity": np.arange(n, dtype=np.uint16)}
    tri = (rng.random((m, 1, 3)) * [10, 6, 4] + rng.normal(0, 0.1, (m, 3, 3))).astype(np.float32)
    fc = {f"{a}{v}": tri[:, v, i] for v in range(3) for i, a in enumerate("xyz")}
    fc["src_face"] = np.arange(m, dtype=np.int64)
    P, F, T = build_tile_tables(pc, fc, SIZE)
    u = len(T["patch"])
    assert T["n_points"].sum() == n and T["n_faces"].sum() == m
    assert T["n_points"].dtype == np.int32 and T["label"].dtype == np.int8 and T["score"].dtype == np.float32
    # rows are the input rows, permuted
    assert np.array_equal(np.sort(P["intensity"]), pc["intensity"])
    assert np.array_equal(P["x"], xyz[P["intensity"].astype(int), 0])
    assert np.array_equal(P["patch"], pack_patch_key(patch_index(np.stack([P["x"], P["y"], P["z"]], 1), SIZE)))
    assert np.array_equal(F["patch"], pack_patch_key(face_patches(tri[F["src_face"]], SIZE)))
    for r in rng.choice(u, 30, replace=False):
        s, e = T["point_start"][r], T["point_stop"][r]
        fs, fe = T["face_start"][r], T["face_stop"][r]
        assert (P["patch"][s:e] == T["patch"][r]).all() and (F["patch"][fs:fe] == T["patch"][r]).all()
        content = np.concatenate([np.stack([P["x"][s:e], P["y"][s:e], P["z"][s:e]], 1),
                                  tri[F["src_face"][fs:fe]].reshape(-1, 3)])
        assert np.array_equal([T["xmin"][r], T["ymin"][r], T["zmin"][r]], content.min(0))
        assert np.array_equal([T["xmax"][r], T["ymax"][r], T["zmax"][r]], content.max(0))
    assert (T["label"] == -1).all() and np.isnan(T["score"]).all() and not T["outlier"].any()


def test_build_tile_tables_points_only():
    xyz = np.array([[0.5, 0.5, 0.5], [3.0, 0.5, 0.5]], np.float32)
    _, F, T = build_tile_tables({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, None, SIZE)
    assert F == {} and T["n_faces"].tolist() == [0, 0] and T["face_start"].tolist() == [0, 0]
    assert T["xmin"].tolist() == [0.5, 3.0]


def test_build_tile_tables_keys_float32_coordinates():
    # 0.99999999 (float64) lies in row j = 0 but is stored as float32 1.0, i.e. row j = 1: key what is stored
    cols = {"x": np.array([0.5]), "y": np.array([0.99999999]), "z": np.array([0.1])}
    P, _, T = build_tile_tables(cols, None, SIZE)
    assert P["y"].dtype == np.float32 and P["y"][0] == 1.0
    assert T["j"].tolist() == [1]
