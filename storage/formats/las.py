"""LAS / LAZ: reading (header, streamed points, truncation checks) and a chunked LAS 1.4 / LAZ writer.

``las_info(path) -> CloudInfo`` and ``iter_las(path, chunk_points, start, stop) -> Iterator[PointChunk]``
are the LAS entry of the reader registry in :mod:`storage.formats.points`, which is the public API;
:class:`LasChunkWriter` and :func:`write_points` (:mod:`storage.formats.las_write`, re-exported here) write
LAS 1.4 / LAZ (lazrs) atomically.

Coordinates are float64 WORLD metres (LAS integers times scale plus offset). A truncated file is
detected from the header's point count before any point is returned, including a LAZ whose chunk
table was cut off ("truncated after K of N points").
"""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator
from pathlib import Path

import laspy
import numpy as np

from storage.errors import InputError
from storage.formats.las_write import LAS_INT32_MAX, LasChunkWriter, choose_offset, write_points
from storage.formats.point_chunk import (
    CloudInfo,
    PointChunk,
    check_cloud_file,
    check_finite_points,
    crs_to_string,
)

# LAS 1.4 point formats 6-10 are compressed in layers; only the ones ms3d stores are decompressed
# (skipping flags, scan angle, user data and point source ids saves ~5-20 % of the decode time).
_D = laspy.DecompressionSelection
DECOMPRESS = (_D.XY_RETURNS_CHANNEL | _D.Z | _D.CLASSIFICATION | _D.INTENSITY | _D.GPS_TIME | _D.RGB
              | _D.ALL_EXTRA_BYTES)


def _open_las(path: Path, selective: bool = False) -> laspy.LasReader:
    check_cloud_file(path)
    with open(path, "rb") as f:
        signature = f.read(4)
    if signature != b"LASF":
        raise InputError(path, f"not a LAS/LAZ file (signature {signature!r}, expected b'LASF')")
    kw = {"decompression_selection": DECOMPRESS} if selective else {}
    try:
        return laspy.open(path, **kw)
    except Exception:  # noqa: BLE001 - EVLRs past the end of a truncated file: retry without them
        try:
            return laspy.open(path, read_evlrs=False, **kw)
        except Exception as err:
            raise InputError(path, f"unreadable LAS header, the file may be truncated ({err})") from err


class _LazWithEmptyChunkTable(io.RawIOBase):
    """Read-only view of a truncated LAZ file whose chunk-table offset is rewritten to point at an empty
    chunk table appended after the surviving bytes, so lazrs decodes the surviving chunks in order."""

    def __init__(self, path: Path, offset_field_at: int):
        self._f = open(path, "rb")  # noqa: SIM115 - closed by close()
        self._size = path.stat().st_size
        self._patch_at = offset_field_at
        self._patch = struct.pack("<q", self._size)
        self._tail = struct.pack("<II", 0, 0)  # chunk-table version 0, zero chunks
        self._pos = 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, pos: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self._size + len(self._tail)}[whence]
        self._pos = max(0, base + pos)
        return self._pos

    def readinto(self, buf) -> int:
        total = self._size + len(self._tail)
        n = max(0, min(len(buf), total - self._pos))
        self._f.seek(min(self._pos, self._size))
        data = bytearray(self._f.read(max(0, min(n, self._size - self._pos))))
        data += self._tail[max(0, self._pos - self._size) : max(0, self._pos + n - self._size)]
        lo, hi = max(self._pos, self._patch_at), min(self._pos + n, self._patch_at + 8)
        if lo < hi:
            data[lo - self._pos : hi - self._pos] = self._patch[lo - self._patch_at : hi - self._patch_at]
        buf[:n] = data
        self._pos += n
        return n

    def close(self) -> None:
        self._f.close()
        super().close()


def _count_decodable_laz_points(path: Path, header: laspy.LasHeader) -> int:
    """Points of a LAZ file whose chunk table is missing (cut off) that still decode, in whole steps."""
    import lazrs

    laszip = header.vlrs.get("LasZipVlr")
    if not laszip:
        return 0
    record = laszip[0].record_data
    item_size = lazrs.LazVlr(record).item_size()
    step, done = 10_000, 0
    with io.BufferedReader(_LazWithEmptyChunkTable(path, header.offset_to_point_data)) as stream:
        stream.seek(header.offset_to_point_data)
        try:
            decoder = lazrs.LasZipDecompressor(stream, record)
            while done < header.point_count:
                m = min(step, header.point_count - done)
                decoder.decompress_many(bytearray(m * item_size))
                done += m
        except Exception:  # noqa: BLE001, S110 - lazrs reports running out of data as a generic error
            pass
    return done


def _las_points_available(path: Path, header: laspy.LasHeader) -> int:
    """How many of the header's points the file really holds (cheap except for a cut-off LAZ)."""
    size = path.stat().st_size
    start = header.offset_to_point_data
    if not header.are_points_compressed:
        end = size
        if getattr(header, "number_of_evlrs", 0) and header.start_of_first_evlr:
            end = min(end, header.start_of_first_evlr)
        return max(0, (end - start) // header.point_format.size)
    with open(path, "rb") as f:
        f.seek(start)
        raw = f.read(8)
        table_at = struct.unpack("<q", raw)[0] if len(raw) == 8 else -1
        if table_at <= start and size >= start + 16:  # writer could not patch it: LASzip puts it last
            f.seek(-8, io.SEEK_END)
            table_at = struct.unpack("<q", f.read(8))[0]
    if start < table_at and table_at + 8 <= size:
        return header.point_count
    return _count_decodable_laz_points(path, header)


def las_info(path: Path) -> CloudInfo:
    """Header facts of a LAS/LAZ file (after the truncation check); no points are read."""
    with _open_las(path) as reader:
        h = reader.header
        _check_las_complete(path, h)
        try:
            crs = crs_to_string(h.parse_crs())
        except Exception:  # noqa: BLE001 - an unparsable CRS VLR is reported as unknown, not fatal
            crs = None
        dims = set(h.point_format.dimension_names)
        return CloudInfo(
            path=str(path),
            format=path.suffix.lower(),
            point_count=int(h.point_count),
            bounds=np.array([h.mins, h.maxs], dtype=np.float64),
            crs=crs,
            scale=tuple(float(s) for s in h.scales),
            offset=tuple(float(o) for o in h.offsets),
            has_rgb="red" in dims,
            has_time="gps_time" in dims,
            point_format=int(h.point_format.id),
            version=str(h.version),
        )


def las_header_bounds(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(mins, maxs) (3,) float64 of a LAS/LAZ header, its points unread (a file whose points fail)."""
    with laspy.open(path) as f:
        return np.asarray(f.header.mins, float), np.asarray(f.header.maxs, float)


def _check_las_complete(path: Path, h: laspy.LasHeader) -> None:
    if h.point_count == 0:
        raise InputError(path, "no points (the header's point count is 0)")
    if not (np.isfinite(h.scales).all() and np.isfinite(h.offsets).all()) or not np.all(h.scales):
        raise InputError(path, f"invalid LAS scale {list(h.scales)} or offset {list(h.offsets)}")
    available = _las_points_available(path, h)
    if available < h.point_count:
        raise InputError(path, f"truncated after {available:,} of {h.point_count:,} points")


def chunk_from_las_record(record, h: laspy.LasHeader) -> PointChunk:
    """A laspy point record as a PointChunk: xyz (n, 3) float64 world metres (integers x scale + offset),
    RGB (n, 3) uint16, intensity, GPS time, classification and extra bytes as the point format has them."""
    arr = record.array
    n = len(arr)
    xyz = np.empty((n, 3), dtype=np.float64, order="F")  # column-major: every later step works per axis
    for i, name in enumerate("XYZ"):
        np.multiply(arr[name], h.scales[i], out=xyz[:, i])  # one pass per axis, no temporaries
        xyz[:, i] += h.offsets[i]
    dims = set(h.point_format.dimension_names)
    rgb = None
    if "red" in dims:
        rgb = np.empty((n, 3), dtype=np.uint16, order="F")  # contiguous columns, as stored
        for i, name in enumerate(("red", "green", "blue")):
            rgb[:, i] = arr[name]
    extra = {name: np.array(record[name]) for name in h.point_format.extra_dimension_names}
    return PointChunk(
        xyz=xyz,
        rgb=rgb,
        intensity=np.array(arr["intensity"], dtype=np.uint16),
        gps_time=np.array(arr["gps_time"], dtype=np.float64) if "gps_time" in dims else None,
        classification=np.asarray(record["classification"], dtype=np.uint8).copy(),
        extra=extra,
    )


def _variable_size_chunks(h: laspy.LasHeader) -> bool:
    """Whether a LAZ file's chunks vary in size (COPC's do: one per octree node)."""
    import lazrs

    laszip = h.vlrs.get("LasZipVlr") if h.are_points_compressed else None
    return bool(laszip) and lazrs.LazVlr(laszip[0].record_data).uses_variable_size_chunks()


def iter_las(path: Path, chunk_points: int, start: int = 0, stop: int | None = None) -> Iterator[PointChunk]:
    """Points ``[start, stop)`` of a LAS/LAZ file in chunks of at most ``chunk_points``."""
    with _open_las(path, selective=True) as reader:
        _check_las_complete(path, reader.header)
        yield from _read_range(reader, path, chunk_points, start, stop)


def iter_las_object(f, name: str, chunk_points: int, start: int = 0, stop: int | None = None
                    ) -> Iterator[PointChunk]:
    """Points ``[start, stop)`` of a LAS/LAZ file given as a seekable binary file object ``f`` (a
    :func:`storage.patches.ranges.open_ranged` over an object by URL: only the header, the chunk table and
    the chunks of the range are fetched); ``name`` names the file in errors. The file's completeness is
    the scan's to check (it read the whole header and the point count); a truncated range fails here."""
    f.seek(0)
    signature = f.read(4)
    f.seek(0)
    if signature != b"LASF":
        raise InputError(name, f"not a LAS/LAZ file (signature {signature!r}, expected b'LASF')")
    try:
        reader = laspy.open(f, closefd=False, decompression_selection=DECOMPRESS)
    except Exception as err:  # one line naming the object
        raise InputError(name, f"unreadable LAS header ({err})") from err
    with reader:
        if reader.header.point_count == 0:
            raise InputError(name, "no points (the header's point count is 0)")
        yield from _read_range(reader, name, chunk_points, start, stop)


def _read_range(reader, path, chunk_points: int, start: int, stop: int | None) -> Iterator[PointChunk]:
    """Points ``[start, stop)`` of an open laspy reader in chunks of at most ``chunk_points``."""
    h = reader.header
    n = int(h.point_count)
    stop = n if stop is None else min(stop, n)
    if start >= stop:
        return
    if start and _variable_size_chunks(h):  # lazrs (0.8) seeks wrongly there: decode the points before
        for a in range(0, start, chunk_points):
            reader.read_points(min(chunk_points, start - a))
    elif start:
        reader.seek(start)
    pos = start
    while pos < stop:
        m = min(chunk_points, stop - pos)
        try:
            record = reader.read_points(m)
        except Exception as err:
            raise InputError(path, f"truncated or corrupt after {pos:,} of {n:,} points ({err})") from err
        if len(record) < m:
            raise InputError(path, f"truncated after {pos + len(record):,} of {n:,} points")
        chunk = chunk_from_las_record(record, h)
        check_finite_points(path, chunk.xyz)
        yield chunk
        pos += m


__all__ = ["LAS_INT32_MAX", "LasChunkWriter", "choose_offset", "chunk_from_las_record", "iter_las", "iter_las_object",
           "las_header_bounds", "las_info", "write_points"]
