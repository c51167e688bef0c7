import numpy as np
import pytest

from storage.grid import BITS, GridRangeError, PatchGrid
from tasks.geometry.cells import Partition, partition_cells
from tasks.partition.kernels import (
    build_tile_tables,
    face_cells,
    merge_pair_index,
    partition_faces,
    partition_points,
    point_cells,
    tile_of_faces,
    tile_of_points,
)

SIZE = (2.3, 1.0, 0.7)
GRID = PatchGrid(SIZE, 100.0)
O = (0.0, 0.0, 0.0)
BIAS = 1 << (min(BITS) - 1)
pack_patch_key = PatchGrid.pack
unpack_patch_key = PatchGrid.unpack


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
    ijk = point_cells(pts, GRID, O)
    assert ijk.dtype == np.int64
    assert ijk[:2].tolist() == [[2, 2, 1], [-1, -1, -1]]
    assert ijk[2].tolist() == [0, 0, 0]
    # float32(2.3) = 2.2999999523..., float32(0.7) = 0.69999998..: just below the boundary, computed in float64
    assert ijk[3].tolist() == [0, 1, 0]
    # the same place from another origin: same cells (world-anchored grid)
    shifted = (pts.astype(np.float64) - [1000.0, -2000.0, 0.0]).astype(np.float32)
    assert point_cells(shifted, GRID, (1000.0, -2000.0, 0.0))[:3].tolist() == ijk[:3].tolist()


def test_patch_index_rejects_nan_and_far():
    with pytest.raises(GridRangeError):
        point_cells(np.array([[np.nan, 0, 0]]), GRID, O)
    with pytest.raises(GridRangeError):
        point_cells(np.array([[0, 0, 2.0**16]]), GRID, O)


def test_pack_unpack_round_trip():
    rng = np.random.default_rng(1)
    ijk = rng.integers(-BIAS, BIAS, size=(10_000, 3)).astype(np.int64)
    ijk[:3] = [[-BIAS, -BIAS, -BIAS], [BIAS - 1, BIAS - 1, BIAS - 1], [0, -1, 1]]
    keys = pack_patch_key(ijk)
    assert keys.dtype == np.int64 and (keys >= 0).all()
    assert np.array_equal(unpack_patch_key(keys), ijk)
    assert len(np.unique(keys)) == len(np.unique(ijk, axis=0))
    # ascending keys == lexicographic (i, j, k)
    lex = np.lexsort((ijk[:, 2], ijk[:, 1], ijk[:, 0]))
    assert (np.diff(keys[lex]) >= 0).all()
    with pytest.raises(ValueError):
        pack_patch_key(np.array([[1 << (BITS[0] - 1), 0, 0]]))
    with pytest.raises(ValueError):
        pack_patch_key(np.array([[0, 0, -(1 << (BITS[2] - 1)) - 1]]))
    # the full field ranges round-trip and stay ordered: UTM northings at 1 m cells fit
    big = np.array([[-(1 << 21), -(1 << 24), -(1 << 15)], [(1 << 21) - 1, (1 << 24) - 1, (1 << 15) - 1],
                    [256_087, 9_999_999, 20]])
    assert np.array_equal(unpack_patch_key(pack_patch_key(big)), big)
    assert (np.diff(pack_patch_key(big[[0, 2, 1]])) > 0).all() and (pack_patch_key(big) >= 0).all()


def test_partition_points_conserves_and_groups():
    rng = np.random.default_rng(2)
    xyz = (rng.random((20_000, 3)) * [30, 20, 10] - [10, 5, 3]).astype(np.float32)
    part = partition_points(xyz, GRID, O)
    _check_partition(part, point_cells(xyz, GRID, O))
    assert np.array_equal(part.ijk, unpack_patch_key(part.keys))


def test_partition_fallback_path_matches():
    """Cells spread so wide that rank + row bits exceed 63: the stable-argsort path gives the same answer."""
    ijk = np.array([[-BIAS, 0, 5], [BIAS - 1, BIAS - 1, -BIAS], [0, 0, 0], [-BIAS, 0, 5], [0, 0, 0]], dtype=np.int64)
    part = partition_cells(ijk)
    _check_partition(part, ijk)
    assert part.order.tolist() == [0, 3, 2, 4, 1]
    assert part.counts.tolist() == [2, 2, 1]


def test_partition_faces_by_centroid():
    # one triangle whose vertices lie in three patches, centroid (1.0, 0.5, 0.3) in patch (0, 0, 0)
    tri = np.array([[[0.1, 0.1, 0.1], [2.5, 0.2, 0.1], [0.4, 1.2, 0.75]],
                    [[-1.0, -1.0, -1.0], [-1.1, -1.0, -1.0], [-1.0, -1.1, -1.0]]], dtype=np.float32)
    assert face_cells(tri, GRID, O).tolist() == [[0, 0, 0], [-1, -2, -2]]
    assert point_cells(tri[0], GRID, O).tolist() == [[0, 0, 0], [1, 0, 0], [0, 1, 1]]
    rng = np.random.default_rng(3)
    tris = (rng.random((5000, 1, 3)) * [20, 20, 5] + rng.normal(0, 0.3, (5000, 3, 3))).astype(np.float32)
    part = partition_faces(tris, GRID, O)
    _check_partition(part, face_cells(tris, GRID, O))


def test_empty_partition():
    part = partition_points(np.zeros((0, 3), np.float32), GRID, O)
    assert part.n_rows == 0 and len(part.keys) == 0


def test_tile_of_patch_uses_centre():
    # patch i = 43 spans x in [98.9, 101.2): straddles the 100 m border, centre 100.05 -> tile 1
    ijk = np.array([[43, 0, 0], [42, 0, 0], [-1, -1, 0], [0, 99, 3]])
    assert GRID.tile_of_cells(ijk).tolist() == [[1, 0], [0, 0], [-1, -1], [0, 0]]
    assert np.allclose(GRID.centre_world(ijk[:1]), [[100.05, 0.5, 0.35]])
    # a point at x = 99.5 lies in patch 43, hence in tile 1 although x < 100
    assert tile_of_points(np.array([[99.5, 10.0, 0.0]]), GRID, O).tolist() == [[1, 0]]
    tri = np.array([[[99.2, 1, 0], [99.4, 1, 0], [99.3, 1.2, 0]]])
    assert tile_of_faces(tri, GRID, O).tolist() == [[1, 0]]
    # tiles are world-anchored too: the same point seen from another origin
    assert tile_of_points(np.array([[-900.5, 10.0, 0.0]]), GRID, (1000.0, 0.0, 0.0)).tolist() == [[1, 0]]


def test_merge_pair_index_union_with_empty_ranges():
    pts = np.array([[0.5, 0.5, 0.2], [0.6, 0.5, 0.2], [5.0, 0.5, 0.2]], np.float32)  # patches (0,0,0), (2,0,0)
    tris = np.array([[[0.1, 0.1, 0.1]] * 3, [[3.0, 0.1, 0.1]] * 3], np.float32)        # (0,0,0), (1,0,0)
    keys, pr, fr = merge_pair_index(partition_points(pts, GRID, O), partition_faces(tris, GRID, O))
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
    P, F, T = build_tile_tables(pc, fc, GRID, O)
    u = len(T["patch"])
    assert T["n_points"].sum() == n and T["n_faces"].sum() == m
    assert T["n_points"].dtype == np.int32 and T["i"].dtype == np.int64
    # rows are the input rows, permuted
    assert np.array_equal(np.sort(P["intensity"]), pc["intensity"])
    assert np.array_equal(P["x"], xyz[P["intensity"].astype(int), 0])
    assert np.array_equal(P["patch"], pack_patch_key(point_cells(np.stack([P["x"], P["y"], P["z"]], 1), GRID, O)))
    assert np.array_equal(F["patch"], pack_patch_key(face_cells(tri[F["src_face"]], GRID, O)))
    for v in range(3):  # Algorithm 1 step 3: the patch of each corner vertex
        assert np.array_equal(F[f"vp{v}"], pack_patch_key(point_cells(tri[F["src_face"], v], GRID, O)))
    for r in rng.choice(u, 30, replace=False):
        s, e = T["point_start"][r], T["point_stop"][r]
        fs, fe = T["face_start"][r], T["face_stop"][r]
        assert (P["patch"][s:e] == T["patch"][r]).all() and (F["patch"][fs:fe] == T["patch"][r]).all()
        content = np.concatenate([np.stack([P["x"][s:e], P["y"][s:e], P["z"][s:e]], 1),
                                  tri[F["src_face"][fs:fe]].reshape(-1, 3)])
        assert np.array_equal([T["xmin"][r], T["ymin"][r], T["zmin"][r]], content.min(0))
        assert np.array_equal([T["xmax"][r], T["ymax"][r], T["zmax"][r]], content.max(0))
    assert set(T) == {"patch", "i", "j", "k", "n_points", "n_faces", "point_start", "point_stop", "face_start",
                      "face_stop", "xmin", "ymin", "zmin", "xmax", "ymax", "zmax"}


def test_build_tile_tables_points_only():
    xyz = np.array([[0.5, 0.5, 0.5], [3.0, 0.5, 0.5]], np.float32)
    _, F, T = build_tile_tables({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, None, GRID, O)
    assert F == {} and T["n_faces"].tolist() == [0, 0] and T["face_start"].tolist() == [0, 0]
    assert T["xmin"].tolist() == [0.5, 3.0]


def test_build_tile_tables_keys_float32_coordinates():
    # 0.99999999 (float64) lies in row j = 0 but is stored as float32 1.0, i.e. row j = 1: key what is stored
    cols = {"x": np.array([0.5]), "y": np.array([0.99999999]), "z": np.array([0.1])}
    P, _, T = build_tile_tables(cols, None, GRID, O)
    assert P["y"].dtype == np.float32 and P["y"][0] == 1.0
    assert T["j"].tolist() == [1]
