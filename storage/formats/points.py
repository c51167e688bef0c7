"""Point-cloud readers (LAS/LAZ, PLY, PCD, XYZ/TXT/CSV) and the public API; LAS/LAZ writer re-exported.

Readers form a registry keyed by extension (``READERS``); every format exposes the same two functions,
``read_header(path) -> CloudInfo`` and ``iter_points(path, chunk_points) -> Iterator[PointChunk]``.
Coordinates come out as float64 WORLD metres in the file's CRS; moving them into the campus frame
(``storage.frame.CampusFrame.to_local``) is the caller's job.

LAS/LAZ reading and the LAS 1.4 / LAZ writer live in :mod:`storage.formats.las`; the shared values
(``PointChunk``, ``CloudInfo``) in :mod:`storage.formats.point_chunk`. Both are re-exported here.

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

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.las import LasChunkWriter, choose_offset, iter_las, las_info, write_points
from storage.formats.point_chunk import (
    CloudInfo,
    PointChunk,
    check_cloud_file,
    check_finite_points,
    crs_to_string,
)

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
    check_cloud_file(path)
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
        check_finite_points(path, np.stack([part["x"], part["y"], part["z"]], axis=1))
    for lo in range(0, lay.count, chunk_points):
        yield _chunk_from_fields(path, np.asarray(rec[lo : lo + chunk_points]))


# --- PCD (open3d), XYZ/TXT/CSV (numpy): read whole, then chunked ---------------------------------


def _read_pcd(path: Path) -> PointChunk:
    import open3d as o3d  # lazily: only PCD needs it

    check_cloud_file(path)
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
    check_cloud_file(path)
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
        check_finite_points(path, whole.xyz)
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


_LAS = CloudFormat(las_info, iter_las)
_PLY = CloudFormat(_info_by_scan(_iter_ply), _iter_ply)
_PCD = CloudFormat(_info_by_scan(_whole_file_format(_read_pcd)), _whole_file_format(_read_pcd))
_XYZ = CloudFormat(_info_by_scan(_whole_file_format(_read_xyz)), _whole_file_format(_read_xyz))
READERS: dict[str, CloudFormat] = {
    ".las": _LAS, ".laz": _LAS, ".ply": _PLY, ".pcd": _PCD, ".xyz": _XYZ, ".txt": _XYZ, ".csv": _XYZ,
}  # fmt: skip


def _format_of(path: Path) -> CloudFormat:
    check_cloud_file(path)
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
    return _scaled(iter_las(path, chunk_points, start, stop), units_scale)


def read_points(path: str | Path, units_scale: float = 1.0) -> PointChunk:
    """The whole file as one PointChunk (small files, tests)."""
    return PointChunk.concat(iter_points(path, units_scale=units_scale))


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
