"""Round trips and bad-input errors of storage.formats.points, on small clouds built here."""

from __future__ import annotations

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.points import (
    LasChunkWriter,
    PointChunk,
    iter_points,
    iter_points_range,
    read_header,
    read_points,
    write_points,
)

N = 30_000


def lattice_chunk(n: int, seed: int, lo_mm, hi_mm) -> PointChunk:
    """n points on a 1 mm lattice at (500000, 4000000, 50) + [lo_mm, hi_mm) millimetres per axis, with every
    LAS field set (random colours, intensities, classes; increasing GPS times)."""
    rng = np.random.default_rng(seed)
    mm = rng.integers(lo_mm, hi_mm, size=(n, 3))
    return PointChunk(
        xyz=np.array([500_000.0, 4_000_000.0, 50.0]) + mm / 1000.0,
        rgb=rng.integers(0, 65536, size=(n, 3)).astype(np.uint16),
        intensity=rng.integers(0, 65536, size=n).astype(np.uint16),
        gps_time=np.sort(rng.uniform(3.0e5, 3.1e5, size=n)),
        classification=rng.integers(0, 20, size=n).astype(np.uint8),
    )


def make_chunk(n: int = N, seed: int = 0) -> PointChunk:
    """UTM-like coordinates (500000, 4000000, 50) +- 1 km (+- 20 m in z), with every field."""
    return lattice_chunk(n, seed, (-1_000_000, -1_000_000, -20_000), (1_000_000, 1_000_000, 20_000))


def assert_same_points(a: PointChunk, b: PointChunk) -> None:
    assert len(a) == len(b)
    assert np.abs(a.xyz - b.xyz).max() < 1e-3  # 1 mm
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.intensity, b.intensity)
    np.testing.assert_array_equal(a.gps_time, b.gps_time)
    np.testing.assert_array_equal(a.classification, b.classification)


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_las_round_trip_keeps_coordinates_fields_and_crs(tmp_path, ext):
    src = make_chunk()
    path = write_points(tmp_path / f"cloud{ext}", src, crs="EPSG:32650")

    info = read_header(path)
    assert info.point_count == N
    assert info.crs == "EPSG:32650"
    assert info.has_rgb and info.has_time and info.point_format == 7 and info.version == "1.4"
    assert info.scale == (0.001, 0.001, 0.001)
    np.testing.assert_allclose(info.bounds, [src.xyz.min(0), src.xyz.max(0)], atol=1e-3)

    back = read_points(path)
    assert_same_points(src, back)
    assert np.abs(src.xyz - back.xyz).max() < 1e-6  # lattice points survive exactly, not just to 1 mm
    assert back.xyz.dtype == np.float64 and back.rgb.dtype == np.uint16


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_three_chunks_write_the_same_points_as_one(tmp_path, ext):
    src = make_chunk()
    write_points(tmp_path / f"once{ext}", src, crs="EPSG:32650")
    with LasChunkWriter(tmp_path / f"chunked{ext}", crs="EPSG:32650") as writer:
        writer.write(src.take(slice(0, 0)))  # an empty first chunk must not pin the offset at 0
        for part in np.array_split(np.arange(N), 3):
            writer.write(src.take(part))
    assert writer.points_written == N
    once, chunked = read_points(tmp_path / f"once{ext}"), read_points(tmp_path / f"chunked{ext}")
    assert_same_points(once, chunked)
    np.testing.assert_array_equal(once.xyz, chunked.xyz)


def test_chunk_iterator_respects_the_chunk_size(tmp_path):
    path = write_points(tmp_path / "c.laz", make_chunk())
    sizes = [len(c) for c in iter_points(path, chunk_points=7_000)]
    assert sizes == [7_000] * 4 + [2_000]
    assert read_header(path).crs is None


def test_extra_dims_and_units_scale(tmp_path):
    src = make_chunk(1000)
    src.extra["range_m"] = np.linspace(0, 100, 1000).astype(np.float32)
    path = write_points(tmp_path / "x.las", src, extra_dims={"range_m": np.float32})
    back = read_points(path)
    np.testing.assert_array_equal(back.extra["range_m"], src.extra["range_m"])
    feet = read_points(path, units_scale=0.3048)
    np.testing.assert_allclose(feet.xyz, back.xyz * 0.3048)


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_range_reads_over_two_halves_equal_the_whole(tmp_path, ext):
    path = write_points(tmp_path / f"r{ext}", make_chunk(), crs="EPSG:32650")
    whole = read_points(path)
    half = N // 2 + 123  # not on a LAZ chunk boundary
    first = PointChunk.concat(iter_points_range(path, 0, half, chunk_points=4_000))
    second = PointChunk.concat(iter_points_range(path, half, N + 10, chunk_points=4_000))
    both = PointChunk.concat([first, second])
    assert len(first) == half and len(second) == N - half
    np.testing.assert_array_equal(both.xyz, whole.xyz)
    np.testing.assert_array_equal(both.gps_time, whole.gps_time)


@pytest.mark.parametrize("ext", [".las", ".laz"])
def test_truncated_file_is_reported_with_points_left(tmp_path, ext):
    path = write_points(tmp_path / f"t{ext}", make_chunk(120_000))  # LAZ: 3 chunks of 50,000
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 3 // 4])
    with pytest.raises(InputError, match=r"truncated after [\d,]+ of 120,000 points") as err:
        read_header(path)
    assert str(path) in str(err.value)
    with pytest.raises(InputError, match="truncated"):
        list(iter_points(path))
    kept = int(err.value.problem.split("after ")[1].split(" of")[0].replace(",", ""))
    assert 0 < kept < 120_000
    if ext == ".las":  # uncompressed: exact count of whole records left
        header_len = len(data) - 120_000 * 36
        assert kept == (len(data) * 3 // 4 - header_len) // 36


def test_truncated_laz_cut_in_half(tmp_path):
    path = write_points(tmp_path / "half.laz", make_chunk())
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated"):
        list(iter_points(path))


def test_empty_las_has_no_points(tmp_path):
    path = write_points(tmp_path / "empty.las", PointChunk(xyz=np.zeros((0, 3))), crs="EPSG:32650")
    with pytest.raises(InputError, match="no points"):
        read_header(path)
    with pytest.raises(InputError, match="no points"):
        list(iter_points(path))


def test_bad_inputs_name_the_file(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_header(tmp_path / "missing.las")
    (tmp_path / "zero.laz").write_bytes(b"")
    with pytest.raises(InputError, match="empty file"):
        read_header(tmp_path / "zero.laz")
    (tmp_path / "fake.las").write_bytes(b"PK\x03\x04" + b"\0" * 400)
    with pytest.raises(InputError, match="signature") as err:
        read_header(tmp_path / "fake.las")
    assert "fake.las" in str(err.value)
    (tmp_path / "cloud.fls").write_bytes(b"x")
    with pytest.raises(InputError, match=r"supported: .*\.e57.*\.las.*\.laz.*\.ply"):
        iter_points(tmp_path / "cloud.fls")


def test_failed_write_leaves_no_file(tmp_path):
    bad = make_chunk(10)
    bad.xyz[3] = np.nan
    with pytest.raises(ValueError, match="NaN"), LasChunkWriter(tmp_path / "w.laz") as writer:
        writer.write(make_chunk(10))
        writer.write(bad)
    assert list(tmp_path.iterdir()) == []


def test_xyz_with_nan_reports_the_count(tmp_path):
    rows = ["500000.0 4000000.0 50.0 10 20 30 7"] * 5 + ["nan 4000000.0 50.0 1 2 3 4"] * 2
    rows += ["500000.0 inf 50.0 1 2 3 4"]
    path = tmp_path / "scan.xyz"
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError, match="3 of 8 points have NaN") as err:
        list(iter_points(path))
    assert "scan.xyz" in str(err.value)


def test_xyz_columns_header_and_comma(tmp_path):
    path = tmp_path / "scan.csv"
    path.write_text("x,y,z,r,g,b,i\n# comment\n1.5,2.5,3.5,255,0,10,100\n4,5,6,0,128,0,7\n")
    pts = read_points(path)
    np.testing.assert_array_equal(pts.xyz, [[1.5, 2.5, 3.5], [4, 5, 6]])
    np.testing.assert_array_equal(pts.rgb, [[65535, 0, 2570], [0, 128 * 257, 0]])
    np.testing.assert_array_equal(pts.intensity, [100, 7])
    assert read_header(path).point_count == 2


def write_binary_ply(path, xyz, rgb8, extra_header=""):
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(xyz)}\nproperty double x\nproperty double y\nproperty double z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty float scalar_intensity\n"
        f"{extra_header}end_header\n"
    )
    rec = np.zeros(len(xyz), dtype=[("p", "<f8", 3), ("c", "u1", 3), ("s", "<f4")])
    rec["p"], rec["c"], rec["s"] = xyz, rgb8, 0.5
    path.write_bytes(header.encode() + rec.tobytes())


def test_binary_ply_streams_in_chunks_with_float64(tmp_path):
    src = make_chunk(5000)
    rgb8 = (src.rgb >> 8).astype(np.uint8)
    path = tmp_path / "cloud.ply"
    write_binary_ply(path, src.xyz, rgb8)
    chunks = list(iter_points(path, chunk_points=2000))
    assert [len(c) for c in chunks] == [2000, 2000, 1000]
    back = PointChunk.concat(chunks)
    np.testing.assert_array_equal(back.xyz, src.xyz)
    np.testing.assert_array_equal(back.rgb, rgb8.astype(np.uint16) * 257)
    assert back.intensity is None and np.all(back.extra["scalar_intensity"] == 0.5)
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(InputError, match="truncated after 4,996 of 5,000 points"):
        read_header(path)


def test_ascii_ply_and_pcd(tmp_path):
    ply = tmp_path / "a.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
        "property ushort intensity\nend_header\n0 1 2 300\n3 4 5 400\n"
    )
    pts = read_points(ply)
    np.testing.assert_array_equal(pts.xyz, [[0, 1, 2], [3, 4, 5]])
    np.testing.assert_array_equal(pts.intensity, [300, 400])
    pcd = tmp_path / "a.pcd"
    pcd.write_text(
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 2\nHEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\nPOINTS 2\nDATA ascii\n500000.123 4000000.456 50.5\n500001 4000001 51\n"
    )
    pts = read_points(pcd)
    np.testing.assert_allclose(pts.xyz, [[500000.123, 4000000.456, 50.5], [500001, 4000001, 51]], atol=1e-6)


def test_chunked_laz_read_equals_laspy_read(tmp_path):
    import laspy

    path = write_points(tmp_path / "c.laz", make_chunk(), crs="EPSG:32650")
    ref = laspy.read(path)
    got = PointChunk.concat(iter_points_range(path, 0, N, chunk_points=3_333))
    np.testing.assert_array_equal(got.xyz, np.stack([ref.x, ref.y, ref.z], axis=1))
    np.testing.assert_array_equal(got.intensity, np.asarray(ref.intensity))
    np.testing.assert_array_equal(got.gps_time, np.asarray(ref.gps_time))
    np.testing.assert_array_equal(got.rgb, np.stack([ref.red, ref.green, ref.blue], axis=1))
