import json

import numpy as np
import pyarrow.parquet as pq
import pytest

from storage.errors import InputError
from storage.grid import PatchGrid
from storage.ids import PatchId
from storage.patches.read import PatchStore, read_side_table
from storage.patches.schema import FACE_DTYPES, PATCH_DTYPES, POINT_DTYPES, TileMeta
from storage.patches.write import write_side_table, write_tile_tables
from tasks.partition.kernels import build_tile_tables

SIZE = (2.3, 1.0, 0.7)
GRID = PatchGrid(SIZE, 100.0)
ORIGIN = (500_000.0, 4_000_000.0, 0.0)
pack_patch_key = PatchGrid.pack
META = TileMeta(tile="3_-2", patch_size_m=SIZE, crs="EPSG:32650", textures=("tex/a.jpg", "tex/b.jpg"))


def _tile(n=10_000, m=1_500, seed=0):
    rng = np.random.default_rng(seed)
    xyz = (rng.random((n, 3)) * [23, 10, 7] + [300, -200, 0]).astype(np.float32)
    points = {
        "x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2],
        "intensity": rng.integers(0, 65535, n).astype(np.uint16),
        "gps_time": rng.random(n) * 1e3 + 3e5,
        "red": rng.integers(0, 65535, n).astype(np.uint16),
        "green": rng.integers(0, 65535, n).astype(np.uint16),
        "blue": rng.integers(0, 65535, n).astype(np.uint16),
        "classification": rng.integers(0, 20, n).astype(np.uint8),
        "source": rng.integers(0, 3, n).astype(np.uint32) * 1_000_000_000,
    }
    tri = (rng.random((m, 1, 3)) * [23, 10, 7] + [300, -200, 0] + rng.normal(0, 0.2, (m, 3, 3))).astype(np.float32)
    faces = {f"{a}{v}": tri[:, v, i] for v in range(3) for i, a in enumerate("xyz")}
    uv = rng.random((m, 6)).astype(np.float32)
    uv[::7] = np.nan
    faces.update({f"{a}{v}": uv[:, 2 * v + i] for v in range(3) for i, a in enumerate("uv")})
    faces["texture"] = np.where(np.isnan(uv[:, 0]), -1, rng.integers(0, 2, m)).astype(np.int16)
    faces.update({c: rng.integers(0, 255, m).astype(np.uint8) for c in ("red", "green", "blue")})
    faces["src_face"] = np.arange(m, dtype=np.int64) * 3
    faces["source"] = np.full(m, 2_000_000_001, dtype=np.uint32)
    vid = (np.int64(2_000_000_001) << 32) | rng.integers(0, 5 * m, (m, 3))
    faces.update({f"vid{v}": vid[:, v] for v in range(3)})
    nrm = rng.normal(size=(m, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    faces.update({c: nrm[:, i].astype(np.float32) for i, c in enumerate(("nx", "ny", "nz"))})
    return build_tile_tables(points, faces, GRID, ORIGIN)


def _same(a: np.ndarray, b: np.ndarray) -> bool:
    """Bitwise equality (NaN == NaN)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def test_round_trip_is_bitwise(tmp_path):
    P, F, T = _tile()
    summary = write_tile_tables(tmp_path / "t", P, F, T, META)
    assert (summary.n_points, summary.n_faces, summary.n_patches) == (10_000, 1_500, len(T["patch"]))
    store = PatchStore(tmp_path / "t")
    assert store.meta == META
    patches = store.patches()
    assert list(patches) == list(PATCH_DTYPES)
    assert all(_same(patches[c], T[c]) for c in T)
    points, faces = store.read_all()
    assert list(points) == list(POINT_DTYPES) and list(faces) == list(FACE_DTYPES)
    assert all(_same(points[c], P[c]) for c in P)
    assert all(_same(faces[c], F[c]) for c in F)
    md = json.loads(pq.ParquetFile(tmp_path / "t" / "faces.parquet").schema_arrow.metadata[b"ms3d"])
    assert md == {"schema_version": 2, "table": "faces", "units": "metre",
                  "frame": "campus-local float32 offsets from campus.json origin", "patch_size_m": [2.3, 1.0, 0.7],
                  "tile": "3_-2", "crs": "EPSG:32650", "n_rows": 1500, "textures": ["tex/a.jpg", "tex/b.jpg"]}
    assert sorted(p.name for p in (tmp_path / "t").iterdir()) == ["faces.parquet", "patches.parquet", "points.parquet"]


def test_read_patch_reads_only_its_row_groups(tmp_path):
    P, F, T = _tile()
    write_tile_tables(tmp_path, P, F, T, META, row_group_size=100)
    assert pq.ParquetFile(tmp_path / "points.parquet").metadata.num_row_groups == 100
    store = PatchStore(tmp_path)
    busiest = int(np.argmax(T["n_points"]))
    for r in [0, busiest, len(T["patch"]) - 1]:
        before = store.stats.points_row_groups_read
        pd = store.read_patch(int(T["patch"][r]))
        assert store.stats.points_row_groups_read - before <= 2
        s, e = T["point_start"][r], T["point_stop"][r]
        assert pd.n_points == e - s and all(_same(pd.points[c], P[c][s:e]) for c in P)
        fs, fe = T["face_start"][r], T["face_stop"][r]
        assert pd.n_faces == fe - fs and all(_same(pd.faces[c], F[c][fs:fe]) for c in F)
        assert pd.xyz().shape == (e - s, 3) and pd.triangles().shape == (fe - fs, 3, 3)
    assert store.stats.rows_read <= 3 * 4 * 100
    by_id = store.read_patch(PatchId(int(T["i"][busiest]), int(T["j"][busiest]), int(T["k"][busiest])))
    assert by_id.key == int(T["patch"][busiest]) and by_id.n_points == T["n_points"][busiest]


def test_read_patches_batch_and_columns(tmp_path):
    P, F, T = _tile(seed=1)
    write_tile_tables(tmp_path, P, F, T, META, row_group_size=500)
    store = PatchStore(tmp_path)
    rows = np.array([7, 3, 400, 401, 402])
    keys = T["patch"][rows]
    out = store.read_patches(list(keys) + [PatchId(int(T["i"][9]), int(T["j"][9]), int(T["k"][9]))],
                             point_columns=["x", "y", "z"], face_columns=["x0"])
    assert [d.key for d in out] == list(keys) + [int(T["patch"][9])]
    for d, r in zip(out, list(rows) + [9]):
        s, e = T["point_start"][r], T["point_stop"][r]
        assert list(d.points) == ["x", "y", "z"] and _same(d.points["z"], P["z"][s:e])
        assert _same(d.faces["x0"], F["x0"][T["face_start"][r]:T["face_stop"][r]])
    with pytest.raises(KeyError):
        store.read_patch(int(pack_patch_key(np.array([[0, 0, 0]]))[0]))
    with pytest.raises(KeyError):
        store.read_patch(PatchId(0, 0, 0))


def test_empty_sides_and_defaults(tmp_path):
    xyz = np.array([[0.5, 0.5, 0.5], [3.0, 0.5, 0.5], [3.1, 0.6, 0.5]], np.float32)
    P, _, T = build_tile_tables({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}, None, GRID, ORIGIN)
    write_tile_tables(tmp_path, P, None, T, TileMeta("0_0", SIZE))
    store = PatchStore(tmp_path)
    assert store.n_faces == 0 and store.meta.textures == () and store.meta.crs is None
    d = store.read_patch(int(T["patch"][1]))
    assert d.n_points == 2 and d.n_faces == 0 and d.faces["texture"].dtype == np.int16
    assert d.points["intensity"].tolist() == [0, 0]  # defaults for missing optional columns
    assert store.stats.faces_row_groups_read == 0


def test_rejects_inconsistent_tables(tmp_path):
    P, F, T = _tile(n=500, m=50)
    bad = dict(T, n_points=T["n_points"] + 1)
    with pytest.raises(ValueError):
        write_tile_tables(tmp_path, P, F, bad, META)
    with pytest.raises(ValueError, match="unknown"):
        write_tile_tables(tmp_path, dict(P, colour=P["x"]), F, T, META)
    unsorted = dict(P, patch=P["patch"][::-1].copy())
    with pytest.raises(ValueError, match="sorted"):
        write_tile_tables(tmp_path, unsorted, F, T, META)
    assert not (tmp_path / "patches.parquet").exists()


def test_corrupt_and_missing_files_name_the_file(tmp_path):
    P, F, T = _tile(n=2000, m=100)
    write_tile_tables(tmp_path, P, F, T, META)
    pts = tmp_path / "points.parquet"
    data = pts.read_bytes()
    pts.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="points.parquet"):
        PatchStore(tmp_path)
    pts.write_bytes(b"not parquet at all" * 10)
    with pytest.raises(InputError, match="points.parquet") as e:
        PatchStore(tmp_path)
    assert e.value.path == str(pts)
    pts.unlink()
    with pytest.raises(InputError, match="points.parquet.*missing"):
        PatchStore(tmp_path)
    (tmp_path / "patches.parquet").unlink()
    with pytest.raises(InputError, match="patches.parquet"):
        PatchStore(tmp_path)


def test_schema_version_mismatch(tmp_path):
    P, F, T = _tile(n=300, m=30)
    write_tile_tables(tmp_path, P, F, T, META)
    path = tmp_path / "patches.parquet"
    table = pq.read_table(path)
    md = json.loads(table.schema.metadata[b"ms3d"])
    md["schema_version"] = 99
    pq.write_table(table.replace_schema_metadata({b"ms3d": json.dumps(md).encode()}), path)
    with pytest.raises(InputError, match="schema_version"):
        PatchStore(tmp_path)


def test_mismatched_files_detected(tmp_path):
    P, F, T = _tile(n=300, m=30)
    write_tile_tables(tmp_path / "a", P, F, T, META)
    P2, F2, T2 = _tile(n=400, m=30, seed=5)
    write_tile_tables(tmp_path / "b", P2, F2, T2, META)
    (tmp_path / "b" / "points.parquet").replace(tmp_path / "a" / "points.parquet")
    with pytest.raises(InputError, match="does not belong"):
        PatchStore(tmp_path / "a")


def test_side_tables_are_aligned_and_never_joined_stale(tmp_path):
    P, F, T = _tile(n=1000, m=100)
    write_tile_tables(tmp_path, P, F, T, META)
    u = len(T["patch"])
    label = (np.arange(u) % 2).astype(np.int8)
    score = np.linspace(0, 1, u).astype(np.float32)
    write_side_table(tmp_path, "labels", {"patch": T["patch"], "label": label}, META)
    write_side_table(tmp_path, "grades", {"patch": T["patch"], "score": score, "grade": label}, META, model_hash="abc")
    store = PatchStore(tmp_path)
    assert _same(store.side("labels")["label"], label) and _same(store.side("grades")["score"], score)
    assert store.side("outliers") is None  # never written
    assert read_side_table(tmp_path, "grades")[1]["model_hash"] == "abc"
    assert _same(store.patches()["point_start"], T["point_start"]) and store.meta == META
    with pytest.raises(ValueError):
        write_side_table(tmp_path, "labels", {"patch": T["patch"]}, META)
    with pytest.raises(ValueError):
        write_side_table(tmp_path, "labels", {"patch": T["patch"], "label": np.full(u, 300)}, META)
    # a side table written for other patches is stale: refused, not joined
    write_side_table(tmp_path, "labels", {"patch": T["patch"][:-1], "label": label[:-1]}, META)
    with pytest.raises(InputError, match="stale"):
        PatchStore(tmp_path).side("labels")


def test_v2_face_columns_and_v1_refused(tmp_path):
    P, F, T = _tile(n=300, m=60)
    write_tile_tables(tmp_path, P, F, T, META)
    store = PatchStore(tmp_path)
    d = store.read_patch(int(T["patch"][np.argmax(T["n_faces"])]))
    assert d.vertex_ids().dtype == np.int64 and d.vertex_ids().shape == (d.n_faces, 3)
    assert np.allclose(np.linalg.norm(d.normals(), axis=1), 1.0, atol=1e-6)
    assert (d.faces["source"] == 2_000_000_001).all() and d.faces["source"].dtype == np.uint32
    path = tmp_path / "faces.parquet"
    table = pq.read_table(path)
    md = json.loads(table.schema.metadata[b"ms3d"])
    md["schema_version"] = 1
    pq.write_table(table.replace_schema_metadata({b"ms3d": json.dumps(md).encode()}), path)
    with pytest.raises(InputError, match="v2.*re-run"):
        PatchStore(tmp_path)


@pytest.mark.parametrize("module", ["storage.patches.read", "storage.patches.write", "storage.patches.schema",
                                    "storage.patches"])
def test_each_patch_store_module_imports_on_its_own(module):
    import subprocess
    import sys

    subprocess.run([sys.executable, "-c", f"import {module}"], check=True)
