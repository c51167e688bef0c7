"""COPC (Cloud Optimized Point Cloud, https://copc.io): a LAZ 1.4 file read by bounds, octree node by node.

A COPC file is a LAZ 1.4 file (point format 6, 7 or 8) whose variable-size LAZ chunks are the nodes of an
octree. Its first VLR, the *COPC info* (user_id ``copc``, record 1, 160 bytes), gives the root cube (centre
and half side in the file's world coordinates) and where the root page of the *hierarchy* lies; the
hierarchy (the EVLR ``copc`` / 1000) lists for each node its VoxelKey (level, x, y, z), the file offset and
byte size of its LAZ chunk and its point count, and an entry whose point count is -1 points at a child
page. A bounds query reads the header, the hierarchy pages over the box and the chunks of the nodes whose
cube overlaps the box; nothing else is read or decompressed.

Read without bounds, a COPC file is an ordinary LAZ file (the registry's ``.laz`` reader in
:mod:`storage.formats.las`). :func:`iter_copc` returns exactly that reader's points (same file order, same
fields: xyz (n, 3) float64 world metres in the file's CRS, RGB, intensity, GPS time, classification,
extra bytes), restricted to a box and a point range.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from storage.errors import InputError
from storage.formats.las import DECOMPRESS, chunk_from_las_record
from storage.formats.point_chunk import PointChunk, check_cloud_file, check_finite_points

COPC_INFO_BYTES = 160
ENTRY = np.dtype([("level", "<i4"), ("x", "<i4"), ("y", "<i4"), ("z", "<i4"),
                  ("offset", "<u8"), ("byte_size", "<i4"), ("point_count", "<i4")])  # 32 bytes, spec order
_INFO = struct.Struct("<3ddd2Q2d")  # centre x/y/z, halfsize, spacing, root page offset/size, gpstime min/max


@dataclass(frozen=True)
class CopcInfo:
    """The COPC info VLR. centre: root cube centre, world metres; halfsize: half its side (metres);
    spacing: point spacing at the root (metres, halved per level); root_hier_offset / _size: the root
    hierarchy page (absolute byte offset, bytes); gpstime_min / _max: GPS time range (seconds)."""

    center: tuple[float, float, float]
    halfsize: float
    spacing: float
    root_hier_offset: int
    root_hier_size: int
    gpstime_min: float = 0.0
    gpstime_max: float = 0.0

    @classmethod
    def from_bytes(cls, data: bytes) -> CopcInfo:
        v = _INFO.unpack_from(data)
        return cls(tuple(v[0:3]), v[3], v[4], v[5], v[6], v[7], v[8])

    def to_bytes(self) -> bytes:
        """The 160-byte record (88 reserved zero bytes at the end)."""
        head = _INFO.pack(*self.center, self.halfsize, self.spacing, self.root_hier_offset, self.root_hier_size,
                          self.gpstime_min, self.gpstime_max)
        return head + bytes(COPC_INFO_BYTES - len(head))


def node_boxes(info: CopcInfo, entries: np.ndarray) -> np.ndarray:
    """The cubes of hierarchy entries: (n, 2, 3) float64 [min, max] world metres.

    >>> info = CopcInfo((10.0, 0.0, 0.0), 4.0, 1.0, 0, 0)
    >>> e = np.array([(1, 1, 0, 0, 0, 0, 0)], ENTRY)
    >>> node_boxes(info, e).tolist()
    [[[10.0, -4.0, -4.0], [14.0, 0.0, 0.0]]]
    """
    side = 2.0 * info.halfsize / np.exp2(entries["level"].astype(np.float64))[:, None]
    ijk = np.stack([entries["x"], entries["y"], entries["z"]], axis=1).astype(np.float64)
    lo = np.asarray(info.center, np.float64) - info.halfsize + ijk * side
    return np.stack([lo, lo + side], axis=1)


def boxes_overlap(boxes: np.ndarray, box: np.ndarray, pad: float = 0.0) -> np.ndarray:
    """Which of ``boxes`` ((n, 2, 3)) touch ``box`` ((2, k), k = 2 for x/y only or 3), grown by ``pad``
    metres: (n,) bool."""
    k = box.shape[1]
    return np.all((boxes[:, 0, :k] <= box[1] + pad) & (boxes[:, 1, :k] >= box[0] - pad), axis=1)


def is_copc(path: str | Path) -> bool:
    """Whether ``path`` is a LAS 1.4 file whose first VLR is the COPC info (any suffix)."""
    try:
        with open(path, "rb") as f:
            head = f.read(375)
            if len(head) < 104 or head[:4] != b"LASF" or head[24:26] != b"\x01\x04":
                return False
            header_size, = struct.unpack_from("<H", head, 94)
            n_vlrs, = struct.unpack_from("<I", head, 100)
            f.seek(header_size)
            vlr = f.read(54)
    except OSError:
        return False
    return n_vlrs > 0 and len(vlr) == 54 and vlr[2:18].rstrip(b"\0") == b"copc" and vlr[18:20] == b"\x01\x00"


@dataclass
class CopcReadStats:
    """What one read cost: bytes read from the file (header, hierarchy pages, chunks), hierarchy pages and
    octree nodes read, points decompressed and points returned."""

    bytes_read: int = 0
    pages_read: int = 0
    nodes_decoded: int = 0
    points_decoded: int = 0
    points_returned: int = 0


@dataclass(frozen=True)
class _Copc:
    path: Path
    header: laspy.LasHeader
    info: CopcInfo
    laz_vlr: bytes
    size: int


def _read(f, path: Path, at: int, n: int, size: int, what: str, stats: CopcReadStats) -> bytes:
    if at + n > size:
        raise InputError(path, f"truncated: the {what} at byte {at:,} ({n:,} bytes) ends past the end of the file "
                               f"({size:,} bytes)")
    f.seek(at)
    stats.bytes_read += n
    return f.read(n)


def _open(path: Path, f, stats: CopcReadStats) -> _Copc:
    """The LAS header, COPC info and LAZ VLR of an open COPC file (InputError naming what is wrong)."""
    if not is_copc(path):
        raise InputError(path, "not a COPC file (a LAS 1.4 file whose first VLR is the COPC info, user_id 'copc' "
                               "record 1)")
    size = path.stat().st_size
    try:
        header = laspy.LasHeader.read_from(f)
    except Exception as err:  # noqa: BLE001 - laspy raises several types for a cut-off header
        raise InputError(path, f"unreadable LAS header, the file may be truncated ({err})") from None
    stats.bytes_read += header.offset_to_point_data
    f.seek(struct.unpack_from("<H", _read(f, path, 94, 2, size, "header", stats))[0])
    vlr_head = f.read(54)
    length = struct.unpack_from("<H", vlr_head, 20)[0]
    if length != COPC_INFO_BYTES:
        raise InputError(path, f"corrupt COPC info VLR ({length} bytes, expected {COPC_INFO_BYTES})")
    info = CopcInfo.from_bytes(f.read(COPC_INFO_BYTES))
    if info.root_hier_offset == 0 or info.root_hier_size == 0:
        raise InputError(path, "no COPC hierarchy (the COPC info names no root hierarchy page)")
    if not (np.isfinite(info.center).all() and info.halfsize > 0):
        raise InputError(path, f"corrupt COPC info (centre {list(info.center)}, half size {info.halfsize})")
    laz = header.vlrs.get("LasZipVlr")
    if not header.are_points_compressed or not laz:
        raise InputError(path, "not a COPC file: its points are not LAZ-compressed")
    if header.point_count == 0:
        raise InputError(path, "no points (the header's point count is 0)")
    return _Copc(path, header, info, laz[0].record_data, size)


def _read_hierarchy(c: _Copc, f, stats: CopcReadStats, box: np.ndarray | None = None) -> np.ndarray:
    """The data nodes ((n,) ENTRY, point_count > 0) sorted by file offset. With ``box`` ((2, k) world
    metres) child pages whose node lies outside it are not read (their nodes could not overlap it)."""
    todo, seen, data = [(c.info.root_hier_offset, c.info.root_hier_size)], set(), []
    pad = float(np.max(c.header.scales))
    while todo:
        at, n = todo.pop()
        if (at, n) in seen:
            raise InputError(c.path, f"corrupt COPC hierarchy: the page at byte {at:,} is listed twice")
        seen.add((at, n))
        if n % ENTRY.itemsize:
            raise InputError(c.path, f"corrupt COPC hierarchy: the page at byte {at:,} holds {n} bytes, not a whole "
                                     f"number of {ENTRY.itemsize}-byte entries")
        page = np.frombuffer(_read(f, c.path, at, n, c.size, "COPC hierarchy page", stats), ENTRY)
        stats.pages_read += 1
        lvl = page["level"]
        bad = (lvl < 0) | (lvl > 30) | (page["point_count"] < -1)
        for axis in "xyz":
            bad |= (page[axis] < 0) | (page[axis] >= (1 << np.clip(lvl, 0, 30)))
        if bad.any():
            e = page[bad][0]
            raise InputError(c.path, f"corrupt COPC hierarchy: entry {e['level']}-{e['x']}-{e['y']}-{e['z']} "
                                     f"(point count {e['point_count']}) in the page at byte {at:,}")
        child = page[page["point_count"] == -1]
        if box is not None and len(child):
            child = child[boxes_overlap(node_boxes(c.info, child), box, pad)]
        todo.extend(zip(child["offset"].tolist(), child["byte_size"].tolist(), strict=True))
        data.append(page[page["point_count"] > 0])
    nodes = np.concatenate(data)
    return nodes[np.argsort(nodes["offset"], kind="stable")]


def _decode(c: _Copc, f, nodes: np.ndarray, stats: CopcReadStats):
    """Read and decompress the chunks of ``nodes`` (file order) into one laspy point record."""
    import lazrs

    off, size = nodes["offset"].astype(np.int64), nodes["byte_size"].astype(np.int64)
    buf = bytearray(int(size.sum()))
    starts = np.flatnonzero(np.r_[True, off[1:] != off[:-1] + size[:-1]])  # contiguous runs: one read each
    ends = np.r_[starts[1:], len(nodes)]
    pos = 0
    for a, b in zip(starts.tolist(), ends.tolist(), strict=True):
        n = int(off[b - 1] + size[b - 1] - off[a])
        buf[pos:pos + n] = _read(f, c.path, int(off[a]), n, c.size, f"LAZ chunk of octree node {_key(nodes[a])}",
                                 stats)
        pos += n
    h = c.header
    out = np.zeros(int(nodes["point_count"].sum()) * h.point_format.size, np.uint8)
    table = list(zip(nodes["point_count"].tolist(), size.tolist(), strict=True))
    try:
        lazrs.decompress_points_with_chunk_table(bytes(buf), c.laz_vlr, out, table, DECOMPRESS.to_lazrs())
    except Exception as err:  # noqa: BLE001 - lazrs reports corrupt data as a generic error
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InputError(c.path, f"corrupt LAZ data in octree nodes {_key(nodes[0])}..{_key(nodes[-1])} at bytes "
                                 f"{int(off[0]):,}..{int(off[-1] + size[-1]):,} ({msg})") from None
    stats.nodes_decoded += len(nodes)
    stats.points_decoded += int(nodes["point_count"].sum())
    packed = laspy.PackedPointRecord.from_buffer(out, h.point_format)
    return laspy.ScaleAwarePointRecord(packed.array, h.point_format, h.scales, h.offsets)


def _key(e) -> str:
    return f"{e['level']}-{e['x']}-{e['y']}-{e['z']}"


def as_box(bounds) -> np.ndarray:
    """``[[xmin, ymin(, zmin)], [xmax, ymax(, zmax)]]`` as a (2, k) float64 box, k = 2 (x/y) or 3; ValueError
    unless finite with minima <= maxima."""
    box = np.asarray(bounds, np.float64)
    if box.ndim != 2 or box.shape[0] != 2 or box.shape[1] not in (2, 3) or not np.isfinite(box).all():
        raise ValueError(f"bounds must be [[xmin, ymin(, zmin)], [xmax, ymax(, zmax)]], finite; got {bounds!r}")
    if (box[0] > box[1]).any():
        raise ValueError(f"bounds minima exceed maxima: {box.tolist()}")
    return box


def _fmt_box(box: np.ndarray) -> str:
    return ", ".join(f"{a} {box[0, i]:,.2f}..{box[1, i]:,.2f}" for i, a in enumerate("xyz"[: box.shape[1]]))


def _batches(counts: np.ndarray, chunk_points: int) -> Iterator[slice]:
    """Consecutive node slices of about ``chunk_points`` points (a larger node alone)."""
    a, total = 0, 0
    for i, n in enumerate(counts.tolist()):
        if i > a and total + n > chunk_points:
            yield slice(a, i)
            a, total = i, 0
        total += n
    if a < len(counts):
        yield slice(a, len(counts))


def copc_level_counts(path: str | Path, bounds=None) -> np.ndarray:
    """Points per octree level in the nodes over ``bounds`` (as :func:`iter_copc`; None: every node), read
    from the header and the hierarchy alone: (levels,) int64, index = level. Coarse levels are even thinnings
    of the cloud, so their running total says how deep a sample of n points must read."""
    path, stats = Path(path), CopcReadStats()
    box = None if bounds is None else as_box(bounds)
    check_cloud_file(path)
    with open(path, "rb") as f:
        c = _open(path, f, stats)
        nodes = _read_hierarchy(c, f, stats, box)
    if box is not None:
        nodes = nodes[boxes_overlap(node_boxes(c.info, nodes), box, float(np.max(c.header.scales)))]
    return np.bincount(nodes["level"], weights=nodes["point_count"], minlength=1).astype(np.int64)


def iter_copc(path: str | Path, chunk_points: int, bounds=None, start: int = 0, stop: int | None = None,
              stats: CopcReadStats | None = None, max_level: int | None = None) -> Iterator[PointChunk]:
    """The points of a COPC file inside ``bounds`` and the point range ``[start, stop)``, in chunks of at most
    ``chunk_points``, decompressing only the octree nodes that overlap the box and the range.

    bounds: [[xmin, ymin(, zmin)], [xmax, ymax(, zmax)]] world metres in the file's CRS, inclusive; None for
    every point. start / stop: point indices in file order (as :func:`storage.formats.las.iter_las` counts
    them). max_level: only nodes of this octree level or coarser (a thinned cloud; None: every level).
    ``stats`` (optional) accumulates what the read cost. Points come in file order; memory is bounded
    by ``chunk_points`` or the largest node. Raises InputError naming the file for a file that is not COPC,
    has no hierarchy, is truncated or corrupt, and for a box that lies outside the data's bounds.
    """
    path, stats = Path(path), stats if stats is not None else CopcReadStats()
    box = None if bounds is None else as_box(bounds)
    check_cloud_file(path)
    with open(path, "rb") as f:
        c = _open(path, f, stats)
        h = c.header
        data = np.array([h.mins, h.maxs], np.float64)
        if box is not None and not boxes_overlap(data[None], box)[0]:
            raise InputError(path, f"the query box ({_fmt_box(box)}) lies outside the data ({_fmt_box(data)})")
        ranged = start > 0 or stop is not None
        nodes = _read_hierarchy(c, f, stats, None if ranged else box)
        counts = nodes["point_count"].astype(np.int64)
        first = np.cumsum(counts) - counts  # each node's first point index in file order
        if (ranged or box is None) and int(counts.sum()) != h.point_count:
            raise InputError(path, f"the COPC hierarchy lists {int(counts.sum()):,} points, the header "
                                   f"{h.point_count:,}")
        stop = h.point_count if stop is None else min(stop, h.point_count)
        keep = (first < stop) & (first + counts > start)
        if box is not None:
            keep &= boxes_overlap(node_boxes(c.info, nodes), box, float(np.max(h.scales)))
        if max_level is not None:
            keep &= nodes["level"] <= max_level
        nodes, first, counts = nodes[keep], first[keep], counts[keep]
        for part in _batches(counts, chunk_points):
            chunk = chunk_from_las_record(_decode(c, f, nodes[part], stats), h)
            check_finite_points(path, chunk.xyz)
            index = np.repeat(first[part] - (np.cumsum(counts[part]) - counts[part]), counts[part])
            index += np.arange(len(index))
            mask = (index >= start) & (index < stop)
            if box is not None:
                k = box.shape[1]
                mask &= np.all((chunk.xyz[:, :k] >= box[0]) & (chunk.xyz[:, :k] <= box[1]), axis=1)
            if not mask.all():
                chunk = chunk.take(mask)
            stats.points_returned += len(chunk)
            for lo in range(0, len(chunk), chunk_points):
                yield chunk.take(slice(lo, lo + chunk_points)) if len(chunk) > chunk_points else chunk


__all__ = ["COPC_INFO_BYTES", "ENTRY", "CopcInfo", "CopcReadStats", "as_box", "boxes_overlap", "copc_level_counts",
           "is_copc", "iter_copc", "node_boxes"]
