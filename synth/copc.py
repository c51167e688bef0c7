"""A small COPC writer for tests and demos (laspy reads COPC but cannot write it).

The file follows the COPC 1.0 specification (https://copc.io): LAS 1.4, point format 6 or 7, the COPC
info VLR first, the LAZ VLR with variable-size chunks (one chunk per octree node, written by lazrs) and
the hierarchy EVLR (user_id ``copc``, record 1000): a root page and, from ``page_level`` down, one child
page per node of that level, so readers have pages to follow.

The octree: the root cube is the bounding cube of the (quantised) points; at level ``l < max_level`` the
first point (in input order) of each occupied cell of a ``span``-per-node grid goes to its level-``l``
node, and every point left goes to its ``max_level`` node. So every ancestor of a node holds points and
coarse levels are even thinnings of the cloud. Points keep their input order within a node; nodes are
written in (level, x, y, z) order.
"""

from __future__ import annotations

import itertools
import struct
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np

from storage.atomic import atomic_path
from storage.formats.copc import ENTRY, CopcInfo
from storage.formats.las import choose_offset
from storage.formats.point_chunk import PointChunk


@dataclass(frozen=True)
class CopcLayout:
    """What :func:`write_copc` wrote. nodes: (n,) ENTRY of the data nodes in file order; order: (m,) int64,
    the input index of each point in file order; info: the COPC info record; pages: hierarchy pages."""

    nodes: np.ndarray
    order: np.ndarray
    info: CopcInfo
    pages: int


def octree_keys(q: np.ndarray, lo: np.ndarray, side: float, max_level: int, span: int) -> np.ndarray:
    """The VoxelKey (level, x, y, z) of each point: (n, 4) int32.

    q: (n, 3) float64 points inside the cube ``lo + [0, side]^3`` (world metres).

    >>> octree_keys(np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.9, 0.9, 0.9]]), np.zeros(3), 1.0, 1, 1).tolist()
    [[0, 0, 0, 0], [1, 0, 0, 0], [1, 1, 1, 1]]
    """
    level = np.full(len(q), max_level, np.int32)
    left = np.arange(len(q))
    for lvl in range(max_level):
        cell = side / (2**lvl * span)
        vox = np.minimum(np.floor((q[left] - lo) / cell), 2**lvl * span - 1).astype(np.int64)
        _, first = np.unique(vox, axis=0, return_index=True)
        level[left[first]] = lvl
        left = np.delete(left, first)
    node = np.floor((q - lo) / (side / np.exp2(level))[:, None]).astype(np.int64)
    node = np.clip(node, 0, (2**level.astype(np.int64) - 1)[:, None])
    return np.column_stack([level, node]).astype(np.int32)


def _record(chunk: PointChunk, ints: np.ndarray, header: laspy.LasHeader) -> laspy.ScaleAwarePointRecord:
    rec = laspy.ScaleAwarePointRecord.zeros(len(ints), header=header)
    for i, name in enumerate("XYZ"):
        rec[name] = ints[:, i]
    ones = np.ones(len(ints), np.uint8)
    rec["return_number"], rec["number_of_returns"] = ones, ones
    for name in ("intensity", "gps_time", "classification"):
        if getattr(chunk, name) is not None:
            rec[name] = getattr(chunk, name)
    if chunk.rgb is not None and "red" in header.point_format.dimension_names:
        for i, name in enumerate(("red", "green", "blue")):
            rec[name] = chunk.rgb[:, i]
    return rec


def _pages(nodes: np.ndarray, page_level: int | None, at: int) -> tuple[list[bytes], int]:
    """Hierarchy pages starting at byte ``at``: the root page, then one per ``page_level`` node holding
    that node and its descendants (the root page points at it with point count -1)."""
    if page_level is None or not (nodes["level"] >= page_level).any():
        return [nodes.tobytes()], 1
    deep = nodes["level"] >= page_level
    shift = (nodes["level"][deep] - page_level).astype(np.int64)
    anchor = np.stack([nodes[a][deep].astype(np.int64) >> shift for a in "xyz"], axis=1)
    heads, group = np.unique(anchor, axis=0, return_inverse=True)
    children = [nodes[deep][group.ravel() == g] for g in range(len(heads))]
    root = np.concatenate([nodes[~deep], np.zeros(len(heads), ENTRY)])
    pos = at + len(root) * ENTRY.itemsize
    for i, (head, page) in enumerate(zip(heads, children, strict=True)):
        root[(~deep).sum() + i] = (page_level, *head.tolist(), pos, page.nbytes, -1)
        pos += page.nbytes
    return [root.tobytes()] + [p.tobytes() for p in children], 1 + len(children)


def write_copc(path: str | Path, chunk: PointChunk, crs: str | None = None, scale=(0.001, 0.001, 0.001),
               offset=None, max_level: int = 2, span: int = 4, page_level: int | None = None) -> CopcLayout:
    """Write ``chunk`` (xyz (n, 3) float64 world metres; RGB makes point format 7, else 6) as a COPC file.

    max_level: depth of the octree (the root is level 0); span: cells per node side used to thin the
    coarse levels; page_level: nodes of this level and deeper go to child hierarchy pages (None: one page).
    """
    xyz = np.asarray(chunk.xyz, np.float64)
    scale = np.asarray(scale, np.float64)
    offset = choose_offset(xyz) if offset is None else np.asarray(offset, np.float64)
    ints = np.round((xyz - offset) / scale).astype(np.int32)
    q = ints * scale + offset  # the positions the file holds: nodes must contain these
    lo, hi = q.min(axis=0), q.max(axis=0)
    half = float((hi - lo).max()) / 2 * 1.001 + float(scale.max())
    centre = (lo + hi) / 2
    keys = octree_keys(q, centre - half, 2 * half, max_level, span)
    order = np.lexsort((keys[:, 3], keys[:, 2], keys[:, 1], keys[:, 0]))  # stable: input order within a node
    ukeys, first, counts = np.unique(keys[order], axis=0, return_index=True, return_counts=True)

    pf = 7 if chunk.rgb is not None else 6
    header = laspy.LasHeader(point_format=pf, version="1.4")
    header.scales, header.offsets = scale, offset
    header.mins, header.maxs = lo, hi
    if crs is not None:
        import pyproj

        header.add_crs(pyproj.CRS.from_user_input(crs))
    raw = _record(chunk, ints, header).array[order]
    import lazrs

    laz = lazrs.LazVlr.new_for_compression(pf, 0, True)
    gps = chunk.gps_time if chunk.gps_time is not None else np.zeros(1)
    info = CopcInfo(tuple(centre.tolist()), half, 2 * half / span, 0, 0, float(gps.min()), float(gps.max()))
    copc_vlr = laspy.VLR("copc", 1, "COPC info", info.to_bytes())
    header.vlrs.insert(0, copc_vlr)
    header.vlrs.append(laspy.VLR("laszip encoded", 22204, "lazrs variable chunks", laz.record_data()))
    header.are_points_compressed = True
    header.point_count = len(raw)
    header.number_of_points_by_return[0] = len(raw)
    header.number_of_evlrs = 1

    with atomic_path(Path(path)) as tmp, open(tmp, "w+b") as f:
        header.write_to(f)
        start = f.tell()
        compressor = lazrs.ParLasZipCompressor(f, laz)
        cuts = np.r_[first, len(raw)].tolist()
        compressor.compress_chunks([raw[a:b].view(np.uint8) for a, b in itertools.pairwise(cuts)])
        compressor.done()
        f.seek(start)
        table = np.array(lazrs.read_chunk_table(f, laz), np.int64).reshape(-1, 2)
        nodes = np.zeros(len(ukeys), ENTRY)
        for i, a in enumerate(("level", "x", "y", "z")):
            nodes[a] = ukeys[:, i]
        nodes["offset"] = start + 8 + np.cumsum(table[:, 1]) - table[:, 1]
        nodes["byte_size"], nodes["point_count"] = table[:, 1], counts
        f.seek(0, 2)
        header.start_of_first_evlr = f.tell()
        pages, n_pages = _pages(nodes, page_level, header.start_of_first_evlr + 60)
        body = b"".join(pages)
        f.write(struct.pack("<H16sHQ32s", 0, b"copc", 1000, len(body), b"EPT hierarchy") + body)
        info = CopcInfo(info.center, half, info.spacing, header.start_of_first_evlr + 60, len(pages[0]),
                        info.gpstime_min, info.gpstime_max)
        copc_vlr.record_data = info.to_bytes()
        f.seek(0)
        header.write_to(f, ensure_same_size=True)
    return CopcLayout(nodes, order, info, n_pages)


__all__ = ["CopcLayout", "octree_keys", "write_copc"]
