"""Point-cloud readers (LAS/LAZ, COPC, PLY, PCD, XYZ/TXT/CSV, E57) and the public API; LAS/LAZ writer re-exported.

Readers form a registry keyed by extension (``READERS``); every format exposes the same two functions,
``read_header(path) -> CloudInfo`` and ``iter_points(path, chunk_points) -> Iterator[PointChunk]``.
Coordinates come out as float64 WORLD metres in the file's CRS; moving them into the campus frame
(``storage.frame.CampusFrame.to_local``) is the caller's job.

Each format has its module: :mod:`storage.formats.las` (with the LAS 1.4 / LAZ writer), ``ply``, ``pcd``,
``xyz``; this module is their registry and the public API. The shared values
(``PointChunk``, ``CloudInfo``) in :mod:`storage.formats.point_chunk`. Both are re-exported here.

A COPC file (``.copc.laz``, or any LAZ whose first VLR is the COPC info) is a LAZ file to the registry; read
with ``bounds`` (a box), it decompresses only the octree nodes that overlap the box (:mod:`storage.formats.copc`).
Other formats are read whole and filtered: the box gives the same points from the same points in any format.

Memory: LAS/LAZ and binary PLY are streamed, so memory is bounded by ``chunk_points``; E57 one scan at a
time (:mod:`storage.formats.e57`); PCD and XYZ/TXT/CSV are read whole, then chunked.

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

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.copc import as_box, is_copc, iter_copc
from storage.formats.e57 import iter_e57
from storage.formats.las import LasChunkWriter, choose_offset, iter_las, las_info, write_points
from storage.formats.pcd import read_pcd
from storage.formats.ply import iter_ply_points
from storage.formats.point_chunk import (
    CloudInfo,
    PointChunk,
    check_cloud_file,
    check_finite_points,
    crs_to_string,
)
from storage.formats.xyz import read_xyz


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
_PLY = CloudFormat(_info_by_scan(iter_ply_points), iter_ply_points)
_PCD = CloudFormat(_info_by_scan(_whole_file_format(read_pcd)), _whole_file_format(read_pcd))
_XYZ = CloudFormat(_info_by_scan(_whole_file_format(read_xyz)), _whole_file_format(read_xyz))
_E57 = CloudFormat(_info_by_scan(iter_e57), iter_e57)
READERS: dict[str, CloudFormat] = {
    ".las": _LAS, ".laz": _LAS, ".ply": _PLY, ".pcd": _PCD, ".xyz": _XYZ, ".txt": _XYZ, ".csv": _XYZ,
    ".e57": _E57,
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


def _inside(chunks: Iterator[PointChunk], box: np.ndarray) -> Iterator[PointChunk]:
    """The points of ``chunks`` inside ``box`` ((2, k) world metres, inclusive); empty chunks are dropped."""
    k = box.shape[1]
    for chunk in chunks:
        keep = np.all((chunk.xyz[:, :k] >= box[0]) & (chunk.xyz[:, :k] <= box[1]), axis=1)
        if not keep.all():
            chunk = chunk.take(keep)
        if len(chunk):
            yield chunk


def _bounded(path: Path, chunk_points: int, units_scale: float, bounds, start: int = 0,
             stop: int | None = None) -> Iterator[PointChunk]:
    """Points of ``path`` in ``bounds`` (world metres, after ``units_scale``): a COPC file reads only its
    octree nodes over the box (queried in file units, 1 mm wider, then filtered exactly like the others)."""
    box = as_box(bounds)
    if is_copc(path):
        query = box / units_scale + np.array([[-1e-3], [1e-3]]) / units_scale
        chunks = iter_copc(path, chunk_points, query, start, stop)
    elif start or stop is not None:
        chunks = iter_las(path, chunk_points, start, stop)
    else:
        chunks = _format_of(path).iter_points(path, chunk_points)
    return _inside(_scaled(chunks, units_scale), box)


def iter_points(
    path: str | Path, chunk_points: int = 2_000_000, units_scale: float = 1.0, bounds=None
) -> Iterator[PointChunk]:
    """Stream a point cloud as PointChunks of at most ``chunk_points`` points.

    xyz is float64 world metres: file coordinates times ``units_scale`` (e.g. 0.3048 for US feet).
    bounds: ``[[xmin, ymin(, zmin)], [xmax, ymax(, zmax)]]`` world metres: only the points inside (inclusive),
    in file order; a COPC file decompresses only the octree nodes over the box, and a box outside a COPC
    file's bounds is an InputError.
    Errors (InputError) are raised before the first chunk for missing, empty, truncated and NaN files,
    except where only decoding finds them (a corrupt LAZ chunk).
    """
    path = Path(path)
    fmt = _format_of(path)
    if bounds is not None:
        return _bounded(path, chunk_points, units_scale, bounds)
    return _scaled(fmt.iter_points(path, chunk_points), units_scale)


def iter_points_range(
    path: str | Path, start: int, stop: int, chunk_points: int = 2_000_000, units_scale: float = 1.0,
    bounds=None,
) -> Iterator[PointChunk]:
    """Points ``[start, stop)`` of a LAS/LAZ file (``stop`` is clipped to the point count), streamed.

    Disjoint ranges can be read by parallel tasks; their concatenation equals ``iter_points``. With
    ``bounds`` (as :func:`iter_points`) only the range's points inside the box come back; in a COPC file
    only the range's octree nodes over the box are decompressed.
    """
    path = Path(path)
    if _format_of(path) is not _LAS:
        raise InputError(path, "range reads need a LAS or LAZ file")
    if start < 0 or stop < start:
        raise ValueError(f"invalid point range [{start}, {stop})")
    if bounds is not None:
        return _bounded(path, chunk_points, units_scale, bounds, start, stop)
    if is_copc(path):  # the hierarchy locates the range's nodes: no decoding of the points before it
        return _scaled(iter_copc(path, chunk_points, None, start, stop), units_scale)
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
    "as_box",
    "choose_offset",
    "crs_to_string",
    "iter_points",
    "iter_points_range",
    "read_header",
    "read_points",
    "write_points",
]
