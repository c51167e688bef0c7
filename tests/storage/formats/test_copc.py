"""COPC point clouds (storage.formats.copc): files written here by synth.copc and checked with laspy's own
CopcReader; bounds queries return exactly the plain LAZ reader's points inside the box while decompressing
only the octree nodes over it; broken files give one line naming the file."""

from __future__ import annotations

import struct

import laspy
import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.copc import CopcReadStats, copc_level_counts, is_copc, iter_copc
from storage.formats.points import (
    PointChunk,
    iter_points,
    iter_points_range,
    read_header,
    read_points,
    write_points,
)
from synth.copc import write_copc
from tests.storage.formats.test_points import lattice_chunk

N = 12_000
BOX = np.array([[500_010.0, 4_000_005.0], [500_030.0, 4_000_020.0]])  # about 1/7 of the x/y extent


def make_chunk(n: int = N, seed: int = 0) -> PointChunk:
    """A 60 m x 40 m x 8 m cloud on a 1 mm lattice near (500000, 4000000, 50), every LAS field set."""
    return lattice_chunk(n, seed, (0, 0, 0), (60_000, 40_000, 8_000))


def assert_identical(a: PointChunk, b: PointChunk) -> None:
    """Same points in the same order, every field bit for bit."""
    assert len(a) == len(b)
    for name in ("xyz", "rgb", "intensity", "gps_time", "classification"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def inside(xyz: np.ndarray, box: np.ndarray) -> np.ndarray:
    k = box.shape[1]
    return np.all((xyz[:, :k] >= box[0]) & (xyz[:, :k] <= box[1]), axis=1)


@pytest.fixture(scope="module")
def copc(tmp_path_factory):
    """A 3-level COPC with child hierarchy pages from level 2, and its layout."""
    path = tmp_path_factory.mktemp("copc") / "scan.copc.laz"
    return path, write_copc(path, make_chunk(), crs="EPSG:32650", max_level=3, span=4, page_level=2)


@pytest.mark.parametrize("page_level", [None, 1])
def test_laspy_copc_reader_reads_the_written_file(tmp_path, page_level):
    src = make_chunk()
    path = tmp_path / "a.copc.laz"
    layout = write_copc(path, src, crs="EPSG:32650", max_level=2, page_level=page_level)
    assert layout.pages == (1 if page_level is None else 1 + (layout.nodes["level"] == page_level).sum())
    assert layout.nodes["point_count"].sum() == N and (layout.nodes["level"] == 2).any()
    with laspy.CopcReader.open(path) as r:
        assert r.copc_info.hierarchy_root_offset == layout.info.root_hier_offset
        whole = r.query()
        np.testing.assert_allclose(np.stack([whole.x, whole.y, whole.z], axis=1), src.xyz[layout.order], rtol=0,
                                   atol=1e-9)  # lattice points, exactly up to float64 rounding
        np.testing.assert_array_equal(whole.gps_time, src.gps_time[layout.order])
        np.testing.assert_array_equal(np.asarray(whole.red), src.rgb[layout.order, 0])
        part = r.query(bounds=laspy.copc.Bounds(BOX[0], BOX[1]))
        assert len(part) == inside(src.xyz, BOX).sum() > 0
        coarse = r.query(level=0)
        assert len(coarse) == layout.nodes["point_count"][layout.nodes["level"] == 0].sum()
    plain = laspy.read(path)  # also an ordinary LAZ 1.4 file
    assert plain.header.point_count == N and plain.header.point_format.id == 7


def test_whole_copc_equals_the_plain_laz_reader(copc):
    path, layout = copc
    plain = read_points(path)  # the registry's .laz reader (laspy, chunk table)
    assert_identical(PointChunk.concat(iter_copc(path, 1_000)), plain)
    src = make_chunk().take(layout.order)
    np.testing.assert_allclose(plain.xyz, src.xyz, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(plain.gps_time, src.gps_time)
    assert all(len(c) <= 1_000 for c in iter_copc(path, 1_000))
    info = read_header(path)
    assert info.point_count == N and info.crs == "EPSG:32650" and info.has_rgb and info.version == "1.4"


def test_bounds_query_decodes_only_overlapping_nodes(copc, capsys):
    path, layout = copc
    plain = read_points(path)
    stats, whole = CopcReadStats(), CopcReadStats()
    got = PointChunk.concat(iter_copc(path, 100_000, bounds=BOX, stats=stats))
    assert_identical(got, plain.take(inside(plain.xyz, BOX)))
    assert_identical(PointChunk.concat(iter_points(path, bounds=BOX)), got)  # the registry's entry
    list(iter_copc(path, 100_000, stats=whole))
    size = path.stat().st_size
    assert whole.points_decoded == N and whole.nodes_decoded == len(layout.nodes)
    assert stats.points_returned == len(got)
    assert stats.points_decoded < N / 2 and stats.bytes_read < size / 2 and stats.pages_read < whole.pages_read
    print(f"\nCOPC {N:,} points, {len(layout.nodes)} nodes, {size:,} bytes; box of {len(got):,} points: "
          f"{stats.nodes_decoded} nodes, {stats.points_decoded:,} points decoded, {stats.bytes_read:,} bytes read "
          f"({stats.bytes_read / whole.bytes_read:.0%} of the whole file's {whole.bytes_read:,})")
    with laspy.CopcReader.open(path) as r:  # laspy's query: the same points
        ref = r.query(bounds=laspy.copc.Bounds(BOX[0], BOX[1]))
        ref_xyz = np.stack([ref.x, ref.y, ref.z], axis=1)
        np.testing.assert_array_equal(np.unique(ref_xyz, axis=0), np.unique(got.xyz, axis=0))


def test_level_counts_and_a_thinned_read(copc):
    path, layout = copc
    counts = copc_level_counts(path)
    assert counts.tolist() == np.bincount(layout.nodes["level"], weights=layout.nodes["point_count"]).tolist()
    assert counts.sum() == N and len(counts) == 4
    coarse = PointChunk.concat(iter_copc(path, 100_000, max_level=1))
    plain = read_points(path)
    assert_identical(coarse, plain.take(slice(0, counts[:2].sum())))  # nodes are written level by level
    over_box = copc_level_counts(path, BOX)
    assert (over_box <= counts).all() and over_box[0] == counts[0] and over_box.sum() < N / 2


def test_box_with_z_and_units_scale(copc):
    path, _ = copc
    plain = read_points(path)
    box3 = np.array([[500_000.0, 4_000_000.0, 51.0], [500_060.0, 4_000_040.0, 52.5]])
    assert_identical(PointChunk.concat(iter_points(path, bounds=box3)), plain.take(inside(plain.xyz, box3)))
    feet = PointChunk.concat(iter_points(path, units_scale=0.3048, bounds=BOX * 0.3048))
    expect = plain.take(inside(plain.xyz, BOX))
    np.testing.assert_allclose(feet.xyz, expect.xyz * 0.3048)
    assert len(feet) == len(expect)


def test_ranges_with_a_box_concatenate_to_the_box(copc):
    path, _ = copc
    plain = read_points(path)
    parts = [PointChunk.concat(iter_points_range(path, a, a + 5_000, chunk_points=700, bounds=BOX))
             for a in range(0, N, 5_000)]
    assert_identical(PointChunk.concat([p for p in parts if len(p)]), plain.take(inside(plain.xyz, BOX)))
    for a in (0, 5_000, 10_000):  # the same range read through the plain reader, then filtered
        ref = PointChunk.concat(iter_points_range(path, a, a + 5_000))
        got = PointChunk.concat(iter_points_range(path, a, a + 5_000, bounds=BOX))
        expect = ref.take(inside(ref.xyz, BOX))
        assert len(got) == len(expect)
        if len(expect):
            assert_identical(got, expect)


def test_range_reads_of_variable_size_chunks_are_exact(copc):
    """lazrs 0.8 seeks to the wrong point in a LAZ file of variable-size chunks (every COPC file): ranges
    come from the hierarchy (COPC) or from decoding the points before them (storage.formats.las)."""
    from storage.formats.las import iter_las

    path, _ = copc
    plain = read_points(path)
    for a, b in ((100, 5_100), (5_000, 10_000), (11_990, N)):
        assert_identical(PointChunk.concat(iter_las(path, 700, a, b)), plain.take(slice(a, b)))
        assert_identical(PointChunk.concat(iter_points_range(path, a, b, chunk_points=700)), plain.take(slice(a, b)))


def test_box_on_other_formats_filters_the_same_points(tmp_path, copc):
    path, _ = copc
    las = write_points(tmp_path / "same.las", read_points(path))
    assert not is_copc(las) and is_copc(path)
    assert_identical(PointChunk.concat(iter_points(las, bounds=BOX)), PointChunk.concat(iter_points(path, bounds=BOX)))


def _one_line(path, **kw) -> str:
    with pytest.raises(InputError) as e:
        list(iter_copc(path, 10_000, **kw))
    msg = str(e.value)
    assert str(path) in msg and "\n" not in msg
    return msg


def test_broken_copc_files_are_one_line(tmp_path, copc):
    path, layout = copc
    data = path.read_bytes()
    cut = tmp_path / "cut.copc.laz"
    cut.write_bytes(data[: len(data) * 2 // 3])
    assert "truncated" in _one_line(cut) and "hierarchy" in _one_line(cut)

    no_hier = tmp_path / "nohier.copc.laz"
    b = bytearray(data)
    info_at = struct.unpack_from("<H", b, 94)[0] + 54
    struct.pack_into("<2Q", b, info_at + 40, 0, 0)  # root_hier_offset, root_hier_size
    no_hier.write_bytes(bytes(b))
    assert "no COPC hierarchy" in _one_line(no_hier)

    bad_entry = tmp_path / "entry.copc.laz"
    b = bytearray(data)
    struct.pack_into("<i", b, layout.info.root_hier_offset + 4, 99)  # root key x = 99 at level 0
    bad_entry.write_bytes(bytes(b))
    assert "corrupt COPC hierarchy" in _one_line(bad_entry)

    zeroed = tmp_path / "zeroed.copc.laz"
    b = bytearray(data)
    node = layout.nodes[len(layout.nodes) // 2]
    a, n = int(node["offset"]), int(node["byte_size"])
    b[a + n // 4: a + n] = bytes(n - n // 4)
    zeroed.write_bytes(bytes(b))
    assert "corrupt LAZ data in octree nodes" in _one_line(zeroed)

    outside = _one_line(path, bounds=[[0.0, 0.0], [10.0, 10.0]])
    assert "outside the data" in outside and "(x 500,000.00..500,0" in outside

    plain = write_points(tmp_path / "plain.laz", make_chunk(100))
    assert "not a COPC file" in _one_line(plain)
