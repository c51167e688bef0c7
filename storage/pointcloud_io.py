"""Point-cloud readers (LAS/LAZ, PLY, PCD, XYZ/TXT/CSV) and a chunked LAS 1.4 / LAZ writer.

Readers form a registry keyed by extension (``READERS``); every format exposes the same two functions,
``read_header(path) -> CloudInfo`` and ``iter_points(path, chunk_points) -> Iterator[PointChunk]``.
Coordinates come out as float64 WORLD metres in the file's CRS; moving them into the campus frame
(``storage.frame.CampusFrame.to_local``) is the caller's job.

Memory: LAS/LAZ and binary PLY are streamed, so memory is bounded by ``chunk_points``; PCD and
XYZ/TXT/CSV are read whole, then chunked.

Every problem with an input file raises :class:`storage.errors.InputError` naming the file:
missing, empty, no points, not a LAS file, truncated ("truncated after K of N points"),
NaN/inf coordinates (with the count), unsupported extension (listing the supported ones).

Example::

    >>> info = read_header("scan.laz")                          # doctest: +SKIP
    >>> info.point_count, info.crs                               # doctest: +SKIP
    (12000000, 'EPSG:32650')
    >>> for chunk in iter_points("scan.laz", chunk_points=1_000_000):   # doctest: +SKIP
    ...     local = frame.to_local(chunk.xyz, source="scan.laz")
"""

from __future__ import annotations

import contextlib
import io
import itertools
import struct
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Self

import laspy
import numpy as np

from .atomic import atomic_path
from .errors import InputError

LAS_INT32_MAX = 2**31 - 1


@dataclass
class PointChunk:
    """A block of points. All arrays have the same length n.

    xyz: (n, 3) float64, metres, WORLD frame (the file's CRS).
    rgb: (n, 3) uint16 (LAS convention, 0..65535) or None.
    intensity: (n,) uint16 or None.
    gps_time: (n,) float64 seconds (as stored) or None.
    classification: (n,) uint8 (ASPRS classes) or None.
    extra: other named per-point arrays, each (n,) or (n, k).
    """

    xyz: np.ndarray
    rgb: np.ndarray | None = None
    intensity: np.ndarray | None = None
    gps_time: np.ndarray | None = None
    classification: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.xyz)

    def take(self, index) -> PointChunk:
        """The points selected by ``index`` (a slice, boolean mask or integer array)."""
        pick = lambda a: None if a is None else a[index]
        return PointChunk(
            xyz=self.xyz[index],
            rgb=pick(self.rgb),
            intensity=pick(self.intensity),
            gps_time=pick(self.gps_time),
            classification=pick(self.classification),
            extra={k: v[index] for k, v in self.extra.items()},
        )

    @staticmethod
    def concat(chunks: Iterable[PointChunk]) -> PointChunk:
        """One chunk holding all points of ``chunks`` in order; an optional field survives only if
        every chunk has it."""
        chunks = list(chunks)
        if not chunks:
            return PointChunk(xyz=np.zeros((0, 3)))

        def cat(name):
            parts = [getattr(c, name) for c in chunks]
            return None if any(p is None for p in parts) else np.concatenate(parts)

        keys = set.intersection(*(set(c.extra) for c in chunks))
        return PointChunk(
            xyz=np.concatenate([c.xyz for c in chunks]),
            rgb=cat("rgb"),
            intensity=cat("intensity"),
            gps_time=cat("gps_time"),
            classification=cat("classification"),
            extra={k: np.concatenate([c.extra[k] for c in chunks]) for k in sorted(keys)},
        )


@dataclass(frozen=True)
class CloudInfo:
    """What a point-cloud file holds, read without loading it (LAS/LAZ) or with one streamed pass.

    bounds: (2, 3) float64 [min, max] world metres. scale/offset: LAS quantisation (None otherwise).
    crs: "EPSG:nnnn" when pyproj finds a code, another pyproj string when it does not, None if absent.
    """

    path: str
    format: str
    point_count: int
    bounds: np.ndarray = field(compare=False)
    crs: str | None = None
    scale: tuple[float, float, float] | None = None
    offset: tuple[float, float, float] | None = None
    has_rgb: bool = False
    has_time: bool = False
    point_format: int | None = None
    version: str | None = None


def _check_file(path: Path) -> None:
    if not path.exists():
        raise InputError(path, "file not found")
    if path.is_dir():
        raise InputError(path, "is a folder, expected a point-cloud file")
    if path.stat().st_size == 0:
        raise InputError(path, "empty file (0 bytes)")


def _check_finite(path: Path, xyz: np.ndarray) -> None:
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputError(path, f"{int(bad.sum()):,} of {len(xyz):,} points have NaN or infinite coordinates")


def crs_to_string(crs) -> str | None:
    """pyproj CRS -> "EPSG:nnnn" when pyproj can identify a code, else its own string; None -> None."""
    if crs is None:
        return None
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg is not None else crs.to_string()


# --- LAS / LAZ -----------------------------------------------------------------------------------


def _open_las(path: Path) -> laspy.LasReader:
    _check_file(path)
    with open(path, "rb") as f:
        signature = f.read(4)
    if signature != b"LASF":
        raise InputError(path, f"not a LAS/LAZ file (signature {signature!r}, expected b'LASF')")
    try:
        return laspy.open(path)
    except Exception:  # noqa: BLE001 - EVLRs past the end of a truncated file: retry without them
        try:
            return laspy.open(path, read_evlrs=False)
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


def _las_info(path: Path) -> CloudInfo:
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


def _check_las_complete(path: Path, h: laspy.LasHeader) -> None:
    if h.point_count == 0:
        raise InputError(path, "no points (the header's point count is 0)")
    if not (np.isfinite(h.scales).all() and np.isfinite(h.offsets).all()) or not np.all(h.scales):
        raise InputError(path, f"invalid LAS scale {list(h.scales)} or offset {list(h.offsets)}")
    available = _las_points_available(path, h)
    if available < h.point_count:
        raise InputError(path, f"truncated after {available:,} of {h.point_count:,} points")


def _chunk_from_las(record, h: laspy.LasHeader) -> PointChunk:
    arr = record.array
    xyz = np.empty((len(arr), 3), dtype=np.float64)
    for i, name in enumerate("XYZ"):
        xyz[:, i] = arr[name] * h.scales[i] + h.offsets[i]
    dims = set(h.point_format.dimension_names)
    rgb = None
    if "red" in dims:
        rgb = np.stack([arr["red"], arr["green"], arr["blue"]], axis=1).astype(np.uint16)
    extra = {name: np.array(record[name]) for name in h.point_format.extra_dimension_names}
    return PointChunk(
        xyz=xyz,
        rgb=rgb,
        intensity=np.array(arr["intensity"], dtype=np.uint16),
        gps_time=np.array(arr["gps_time"], dtype=np.float64) if "gps_time" in dims else None,
        classification=np.asarray(record["classification"], dtype=np.uint8).copy(),
        extra=extra,
    )


def _iter_las(path: Path, chunk_points: int, start: int = 0, stop: int | None = None) -> Iterator[PointChunk]:
    with _open_las(path) as reader:
        h = reader.header
        n = int(h.point_count)
        _check_las_complete(path, h)
        stop = n if stop is None else min(stop, n)
        if start >= stop:
            return
        if start:
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
            chunk = _chunk_from_las(record, h)
            _check_finite(path, chunk.xyz)
            yield chunk
            pos += m


# --- PLY (own parser: exact dtypes, memory-mapped binary) --------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_ALIASES = {
    "rgb": [("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")],
    "intensity": ["intensity", "Intensity", "scalar_intensity", "scalar_Intensity"],
    "gps_time": ["gps_time", "GpsTime", "scalar_gps_time", "scalar_GpsTime", "time", "timestamp"],
    "classification": ["classification", "Classification", "scalar_classification", "scalar_Classification"],
}


@dataclass(frozen=True)
class _PlyVertexLayout:
    encoding: str  # ascii | binary_little_endian | binary_big_endian
    count: int
    dtype: np.dtype  # one vertex record
    data_start: int  # byte offset of the first vertex (binary) or line index after the header (ascii)


def _ply_vertex_layout(path: Path) -> _PlyVertexLayout:
    elements: list[tuple[str, int, list]] = []
    encoding = None
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(path, "not a PLY file (first line is not 'ply')")
        header_lines = 1
        while True:
            line = f.readline()
            header_lines += 1
            if not line:
                raise InputError(path, "PLY header has no end_header line (truncated?)")
            words = line.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "format":
                encoding = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                props = elements[-1][2]
                if words[1] == "list":
                    props.append((words[4], None))
                elif words[1] in _PLY_TYPES:
                    props.append((words[2], _PLY_TYPES[words[1]]))
                else:
                    raise InputError(path, f"unknown PLY property type {words[1]!r}")
            elif words[0] == "end_header":
                break
        header_len = f.tell()
    if encoding not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(path, f"unsupported PLY format {encoding!r}")
    endian = ">" if encoding == "binary_big_endian" else "<"
    skip_bytes, skip_lines = 0, 0
    for name, count, props in elements:
        if any(t is None for _, t in props):
            if name == "vertex":
                raise InputError(path, "PLY vertex element has list properties; not a point cloud")
            raise InputError(path, f"PLY element {name!r} before 'vertex' has list properties; unsupported")
        dtype = np.dtype([(p, endian + t) for p, t in props])
        if name == "vertex":
            start = header_len + skip_bytes if encoding != "ascii" else header_lines + skip_lines
            return _PlyVertexLayout(encoding, count, dtype, start)
        skip_bytes += count * dtype.itemsize
        skip_lines += count
    raise InputError(path, "PLY file has no 'vertex' element")


def _chunk_from_fields(path: Path, rec: np.ndarray) -> PointChunk:
    """Structured records (PLY vertex properties) -> PointChunk, by the usual property names."""
    names = set(rec.dtype.names)
    if not {"x", "y", "z"} <= names:
        raise InputError(path, f"no x/y/z properties (found {sorted(names)})")
    used = {"x", "y", "z"}
    chunk = PointChunk(xyz=np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64))
    for trio in _ALIASES["rgb"]:
        if set(trio) <= names:
            rgb = np.stack([rec[c] for c in trio], axis=1)
            chunk.rgb = _rgb_to_uint16(rgb, eight_bit=rgb.dtype == np.uint8)
            used |= set(trio)
            break
    for key in ("intensity", "gps_time", "classification"):
        name = next((a for a in _ALIASES[key] if a in names), None)
        if name is None:
            continue
        col = rec[name]
        if key == "intensity" and col.dtype.kind == "f":
            continue  # float reflectance has no uint16 meaning: left in extra under its own name
        target = {"intensity": np.uint16, "gps_time": np.float64, "classification": np.uint8}[key]
        setattr(chunk, key, col.astype(target))
        used.add(name)
    chunk.extra = {n: np.array(rec[n]) for n in rec.dtype.names if n not in used}
    return chunk


def _rgb_to_uint16(rgb: np.ndarray, eight_bit: bool) -> np.ndarray:
    if rgb.dtype.kind == "f":
        return np.clip(np.round(rgb * 65535.0), 0, 65535).astype(np.uint16)
    if eight_bit:
        return rgb.astype(np.uint16) * 257  # 255 -> 65535
    return np.clip(rgb, 0, 65535).astype(np.uint16)


def _iter_ply(path: Path, chunk_points: int) -> Iterator[PointChunk]:
    _check_file(path)
    lay = _ply_vertex_layout(path)
    if lay.count == 0:
        raise InputError(path, "no points (PLY vertex count is 0)")
    if lay.encoding == "ascii":
        with open(path, "r", errors="replace") as f:
            lines = list(itertools.islice(f, lay.data_start, lay.data_start + lay.count))
        if len(lines) < lay.count:
            raise InputError(path, f"truncated after {len(lines):,} of {lay.count:,} points")
        try:
            table = np.loadtxt(lines, ndmin=2, usecols=range(len(lay.dtype.names)))
        except ValueError as err:
            raise InputError(path, f"malformed ASCII PLY vertex line ({err})") from err
        rec = np.empty(lay.count, dtype=lay.dtype)
        for i, name in enumerate(lay.dtype.names):
            rec[name] = table[:, i]
    else:
        available = (path.stat().st_size - lay.data_start) // lay.dtype.itemsize
        if available < lay.count:
            raise InputError(path, f"truncated after {max(available, 0):,} of {lay.count:,} points")
        rec = np.memmap(path, dtype=lay.dtype, mode="r", offset=lay.data_start, shape=(lay.count,))
    for lo in range(0, lay.count, chunk_points):  # a NaN anywhere fails the file before any chunk
        part = rec[lo : lo + chunk_points]
        _check_finite(path, np.stack([part["x"], part["y"], part["z"]], axis=1))
    for lo in range(0, lay.count, chunk_points):
        yield _chunk_from_fields(path, np.asarray(rec[lo : lo + chunk_points]))


# --- PCD (open3d), XYZ/TXT/CSV (numpy): read whole, then chunked ---------------------------------


def _read_pcd(path: Path) -> PointChunk:
    import open3d as o3d  # lazily: only PCD needs it

    _check_file(path)
    try:
        pcd = o3d.t.io.read_point_cloud(str(path))
    except Exception as err:
        raise InputError(path, f"unreadable PCD file ({err})") from err
    attrs = pcd.point
    if "positions" not in attrs or len(attrs["positions"]) == 0:
        raise InputError(path, "no points (or an unreadable PCD file)")
    chunk = PointChunk(xyz=attrs["positions"].numpy().astype(np.float64))
    if "colors" in attrs:
        colors = attrs["colors"].numpy()
        chunk.rgb = _rgb_to_uint16(colors, eight_bit=colors.dtype == np.uint8)
    if "intensity" in attrs:
        val = attrs["intensity"].numpy().reshape(len(chunk.xyz), -1)[:, 0]
        if val.dtype.kind == "f":
            chunk.extra["intensity"] = val
        else:
            chunk.intensity = val.astype(np.uint16)
    return chunk


def _read_xyz(path: Path, block_lines: int = 1_000_000) -> PointChunk:
    """Columns ``x y z [r g b] [intensity]`` (whitespace, comma or semicolon separated; '#' comments;
    one non-numeric header line allowed). RGB columns all within 0..255 are read as 8-bit and scaled to
    16-bit; other column counts keep the columns beyond x y z in ``extra['col3']``, ``extra['col4']``..."""
    _check_file(path)
    with open(path, "r", errors="replace") as f:
        first = ""
        for first in f:
            if first.strip() and not first.lstrip().startswith("#"):
                break
        delimiter = "," if "," in first else (";" if ";" in first else None)
        try:
            [float(t) for t in first.replace(",", " ").replace(";", " ").split()]
            skip = 0
        except ValueError:
            skip = 1
        f.seek(0)
        blocks, line_no = [], 0
        lines = (ln for ln in f if ln.strip() and not ln.lstrip().startswith("#"))
        for _ in range(skip):
            next(lines, None)
        while block := list(itertools.islice(lines, block_lines)):
            try:
                blocks.append(np.loadtxt(block, delimiter=delimiter, ndmin=2, dtype=np.float64))
            except ValueError as err:
                rows = f"{line_no + 1}..{line_no + len(block)}"
                raise InputError(path, f"malformed row among data rows {rows}: {err}") from err
            line_no += len(block)
    if not blocks:
        raise InputError(path, "no points (no data rows)")
    table = np.concatenate(blocks)
    if table.shape[1] < 3:
        raise InputError(path, f"expected at least 3 columns (x y z), found {table.shape[1]}")
    chunk = PointChunk(xyz=np.ascontiguousarray(table[:, :3]))
    ncol = table.shape[1]
    if ncol in (6, 7):
        rgb = table[:, 3:6]
        finite = rgb[np.isfinite(rgb)]
        chunk.rgb = _rgb_to_uint16(rgb.astype(np.int64), eight_bit=finite.size == 0 or finite.max() <= 255)
    if ncol in (4, 7):
        chunk.intensity = np.clip(table[:, -1], 0, 65535).astype(np.uint16)
    if ncol not in (3, 4, 6, 7):
        chunk.extra = {f"col{i}": table[:, i].copy() for i in range(3, ncol)}
    return chunk


def _whole_file_format(read: Callable[[Path], PointChunk]):
    def iter_chunks(path: Path, chunk_points: int) -> Iterator[PointChunk]:
        whole = read(path)
        _check_finite(path, whole.xyz)
        for lo in range(0, len(whole), chunk_points):
            yield whole.take(slice(lo, lo + chunk_points))

    return iter_chunks


def _info_by_scan(iter_chunks: Callable[[Path, int], Iterator[PointChunk]]):
    def info(path: Path) -> CloudInfo:
        n, lo, hi, has_rgb, has_time = 0, np.full(3, np.inf), np.full(3, -np.inf), True, True
        for chunk in iter_chunks(path, 2_000_000):
            n += len(chunk)
            lo, hi = np.minimum(lo, chunk.xyz.min(axis=0)), np.maximum(hi, chunk.xyz.max(axis=0))
            has_rgb &= chunk.rgb is not None
            has_time &= chunk.gps_time is not None
        bounds = np.array([lo, hi])
        return CloudInfo(str(path), path.suffix.lower(), n, bounds, has_rgb=has_rgb, has_time=has_time)

    return info


@dataclass(frozen=True)
class CloudFormat:
    """One reader of the registry: the same two functions for every format."""

    read_header: Callable[[Path], CloudInfo]
    iter_points: Callable[[Path, int], Iterator[PointChunk]]


_LAS = CloudFormat(_las_info, _iter_las)
_PLY = CloudFormat(_info_by_scan(_iter_ply), _iter_ply)
_PCD = CloudFormat(_info_by_scan(_whole_file_format(_read_pcd)), _whole_file_format(_read_pcd))
_XYZ = CloudFormat(_info_by_scan(_whole_file_format(_read_xyz)), _whole_file_format(_read_xyz))
READERS: dict[str, CloudFormat] = {
    ".las": _LAS, ".laz": _LAS, ".ply": _PLY, ".pcd": _PCD, ".xyz": _XYZ, ".txt": _XYZ, ".csv": _XYZ,
}  # fmt: skip


def _format_of(path: Path) -> CloudFormat:
    _check_file(path)
    try:
        return READERS[path.suffix.lower()]
    except KeyError:
        raise InputError(
            path, f"unsupported point-cloud format {path.suffix!r}; supported: {', '.join(sorted(READERS))}"
        ) from None


# --- public reading API ----------------------------------------------------------------------------


def read_header(path: str | Path) -> CloudInfo:
    """Point count, world bounds, CRS, quantisation and fields of a point-cloud file.

    LAS/LAZ: from the header (plus a truncation check); other formats: one streamed pass over the points.
    """
    path = Path(path)
    return _format_of(path).read_header(path)


def _scaled(chunks: Iterator[PointChunk], units_scale: float) -> Iterator[PointChunk]:
    if not (np.isfinite(units_scale) and units_scale > 0):
        raise ValueError(f"units_scale must be a positive number, got {units_scale}")
    for chunk in chunks:
        if units_scale != 1.0:
            chunk.xyz = chunk.xyz * units_scale
        yield chunk


def iter_points(
    path: str | Path, chunk_points: int = 2_000_000, units_scale: float = 1.0
) -> Iterator[PointChunk]:
    """Stream a point cloud as PointChunks of at most ``chunk_points`` points.

    xyz is float64 world metres: file coordinates times ``units_scale`` (e.g. 0.3048 for US feet).
    Errors (InputError) are raised before the first chunk for missing, empty, truncated and NaN files,
    except where only decoding finds them (a corrupt LAZ chunk).
    """
    path = Path(path)
    return _scaled(_format_of(path).iter_points(path, chunk_points), units_scale)


def iter_points_range(
    path: str | Path, start: int, stop: int, chunk_points: int = 2_000_000, units_scale: float = 1.0
) -> Iterator[PointChunk]:
    """Points ``[start, stop)`` of a LAS/LAZ file (``stop`` is clipped to the point count), streamed.

    Disjoint ranges can be read by parallel tasks; their concatenation equals ``iter_points``.
    """
    path = Path(path)
    if _format_of(path) is not _LAS:
        raise InputError(path, "range reads need a LAS or LAZ file")
    if start < 0 or stop < start:
        raise ValueError(f"invalid point range [{start}, {stop})")
    return _scaled(_iter_las(path, chunk_points, start, stop), units_scale)


def read_points(path: str | Path, units_scale: float = 1.0) -> PointChunk:
    """The whole file as one PointChunk (small files, tests)."""
    return PointChunk.concat(iter_points(path, units_scale=units_scale))


# --- LAS 1.4 / LAZ writer --------------------------------------------------------------------------


def choose_offset(xyz: np.ndarray, snap_m: float = 1000.0) -> np.ndarray:
    """A LAS offset near the data: the bounding-box centre snapped to ``snap_m``. (3,) float64.

    At 1 mm scale an int32 reaches +-2147 km from the offset, so any campus fits.
    """
    if len(xyz) == 0:
        return np.zeros(3)
    centre = (xyz.min(axis=0) + xyz.max(axis=0)) / 2.0
    return np.round(centre / snap_m) * snap_m


class LasChunkWriter:
    """Write a LAS 1.4 (``.las``) or LAZ (``.laz``, lazrs) file chunk by chunk, atomically.

    Memory is bounded by the largest chunk. The file appears at ``path`` only when the context exits
    without error (written under a temporary name beside it, then renamed).

    Args:
        path: output ``.las`` / ``.laz``.
        crs: e.g. "EPSG:32650" (anything pyproj accepts), written as a WKT VLR; None writes no CRS.
        scale: (3,) metres per integer step; 1 mm by default.
        offset: (3,) world metres; None chooses one near the first chunk (``choose_offset``).
        point_format: 6 (no colour), 7 (RGB, default) or 8 (RGB + NIR); all carry GPS time.
        extra_dims: {name: numpy dtype} written as LAS extra bytes from ``PointChunk.extra[name]``.

    Example::

        with LasChunkWriter("out.laz", crs="EPSG:32650") as w:
            for chunk in iter_points("in.las"):
                w.write(chunk)
    """

    def __init__(
        self,
        path: str | Path,
        crs: str | None = None,
        scale=(0.001, 0.001, 0.001),
        offset=None,
        point_format: int = 7,
        extra_dims: dict[str, object] | None = None,
    ):
        self.path = Path(path)
        if self.path.suffix.lower() not in (".las", ".laz"):
            raise ValueError(f"{self.path}: LasChunkWriter writes .las or .laz, not {self.path.suffix!r}")
        if point_format not in (6, 7, 8):
            raise ValueError(f"point_format must be 6, 7 or 8 (LAS 1.4), got {point_format}")
        self.header = laspy.LasHeader(point_format=point_format, version="1.4")
        self.header.scales = np.asarray(scale, dtype=np.float64)
        self.extra_dims = {k: np.dtype(v) for k, v in (extra_dims or {}).items()}
        if self.extra_dims:
            params = [laspy.ExtraBytesParams(name=k, type=v) for k, v in self.extra_dims.items()]
            self.header.add_extra_dims(params)
        if crs is not None:
            import pyproj

            self.header.add_crs(pyproj.CRS.from_user_input(crs))
        self._offset = None if offset is None else np.asarray(offset, dtype=np.float64)
        self._stack: contextlib.ExitStack | None = None
        self._writer = None
        self.points_written = 0

    def __enter__(self) -> Self:
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(atomic_path(self.path))
        return self

    def write(self, chunk: PointChunk) -> None:
        """Append the points of ``chunk`` (xyz float64 world metres)."""
        if self._stack is None:
            raise RuntimeError("use LasChunkWriter as a context manager")
        xyz = np.asarray(chunk.xyz, dtype=np.float64)
        bad = ~np.isfinite(xyz).all(axis=1)
        if bad.any():
            raise ValueError(f"{self.path}: refusing to write {int(bad.sum())} NaN/inf points")
        if len(xyz) == 0:  # an empty first chunk must not fix the offset
            return
        if self._writer is None:
            self._open(xyz)
        self._writer.write_points(self._record(chunk, xyz))
        self.points_written += len(xyz)

    def _open(self, xyz: np.ndarray) -> None:
        self.header.offsets = self._offset if self._offset is not None else choose_offset(xyz)
        self._writer = laspy.open(
            self._tmp, mode="w", header=self.header, do_compress=self.path.suffix.lower() == ".laz"
        )

    def _record(self, chunk: PointChunk, xyz: np.ndarray):
        h = self._writer.header
        ints = np.round((xyz - h.offsets) / h.scales)
        if np.abs(ints).max() > LAS_INT32_MAX:
            raise ValueError(
                f"{self.path}: coordinates {xyz.min(axis=0)}..{xyz.max(axis=0)} do not fit LAS int32 at scale "
                f"{list(h.scales)} around offset {list(h.offsets)}; pass an offset nearer the data"
            )
        rec = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=h)
        for i, name in enumerate("XYZ"):
            rec[name] = ints[:, i].astype(np.int32)
        if chunk.intensity is not None:
            rec["intensity"] = chunk.intensity
        if chunk.classification is not None:
            rec["classification"] = chunk.classification
        if chunk.gps_time is not None:
            rec["gps_time"] = chunk.gps_time
        if chunk.rgb is not None and h.point_format.id in (7, 8):
            for i, name in enumerate(("red", "green", "blue")):
                rec[name] = chunk.rgb[:, i]
        for name in self.extra_dims:
            if name not in chunk.extra:
                raise ValueError(f"{self.path}: chunk has no extra field {name!r} declared in extra_dims")
            rec[name] = chunk.extra[name]
        return rec

    def _abandon(self) -> None:
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close()

    def __exit__(self, exc_type, exc, tb):
        stack, self._stack = self._stack, None
        if exc_type is not None:
            self._abandon()
            return stack.__exit__(exc_type, exc, tb)
        try:
            if self._writer is None:  # nothing written: an empty but valid file
                self._open(np.zeros((0, 3)))
            self._writer.close()
        except BaseException:
            self._abandon()
            if not stack.__exit__(*sys.exc_info()):
                raise
            return False
        return stack.__exit__(None, None, None)


def write_points(path: str | Path, chunk: PointChunk, crs: str | None = None, **writer_kwargs) -> Path:
    """Write one PointChunk to a LAS/LAZ file atomically (see LasChunkWriter for the options)."""
    with LasChunkWriter(path, crs=crs, **writer_kwargs) as writer:
        writer.write(chunk)
    return Path(path)


__all__ = [
    "READERS",
    "CloudFormat",
    "CloudInfo",
    "LasChunkWriter",
    "PointChunk",
    "choose_offset",
    "crs_to_string",
    "iter_points",
    "iter_points_range",
    "read_header",
    "read_points",
    "write_points",
]
