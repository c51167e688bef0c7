"""Ingest's pure kernels: the campus frame transform, welded vertex ids, and the staging columns of
points and faces. Arrays in, arrays out; no I/O here.
"""

from __future__ import annotations

import numpy as np

from storage.errors import InputError
from storage.frame import MAX_LOCAL_EXTENT_M, CampusFrame
from storage.inputs import VERTEX_INDEX_BITS
from storage.mesh_io import MeshData
from storage.pointcloud_io import PointChunk
from storage.staging import FACE_VERTEX_COLUMNS


def weld_vertex_index(vertices: np.ndarray) -> np.ndarray:
    """For each vertex, the lowest index of a vertex at exactly the same position.

    vertices: (n, 3) float64 -> (n,) int64. Seam-split vertices (glTF, PLY) get one id, so faces that
    share an edge share its vertex ids.

    >>> weld_vertex_index(np.array([[0., 0, 0], [1, 0, 0], [0, 0, 0]])).tolist()
    [0, 1, 0]
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    if len(v) == 0:
        return np.zeros(0, np.int64)
    rows = v.view(np.dtype((np.void, v.dtype.itemsize * 3))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    return first.astype(np.int64)[inverse.ravel()]


def vertex_ids(source: int, faces: np.ndarray, canonical: np.ndarray) -> np.ndarray:
    """Campus-unique vertex ids ``source << 32 | canonical vertex index``. faces: (m, 3) -> (m, 3) int64."""
    if len(canonical) and canonical.max() >= (1 << VERTEX_INDEX_BITS):
        raise ValueError(f"a mesh file with more than 2**{VERTEX_INDEX_BITS} vertices")
    return (np.int64(source) << VERTEX_INDEX_BITS) | canonical[faces]


def point_columns(chunk: PointChunk, local: np.ndarray, source: int) -> dict[str, np.ndarray]:
    """Staging/patch-store point columns from a chunk and its campus-local float32 xyz (n, 3)."""
    n = len(local)
    rgb = chunk.rgb if chunk.rgb is not None else np.zeros((n, 3), np.uint16, order="F")
    u16 = lambda a: a.astype(np.uint16, copy=False)
    return {
        "x": local[:, 0], "y": local[:, 1], "z": local[:, 2],
        "intensity": chunk.intensity if chunk.intensity is not None else np.zeros(n, np.uint16),
        "gps_time": chunk.gps_time if chunk.gps_time is not None else np.zeros(n, np.float64),
        "red": u16(rgb[:, 0]), "green": u16(rgb[:, 1]), "blue": u16(rgb[:, 2]),
        "classification": chunk.classification if chunk.classification is not None else np.zeros(n, np.uint8),
        "source": np.full(n, source, np.uint32),
    }  # fmt: skip


def face_columns(mesh: MeshData, tri_local: np.ndarray, vids: np.ndarray, normals: np.ndarray,
                 source: int) -> dict[str, np.ndarray]:
    """Staging/patch-store face columns.

    tri_local: (m, 3, 3) float32 campus-local metres; vids: (m, 3) int64 vertex ids; normals: (m, 3) unit.
    """
    m = len(tri_local)
    cols = {f"{a}{v}": tri_local[:, v, ai] for v in range(3) for ai, a in enumerate("xyz")}
    cols = {k: cols[k] for k in FACE_VERTEX_COLUMNS}
    for v in range(3):
        cols[f"vid{v}"] = vids[:, v]
    cols["nx"], cols["ny"], cols["nz"] = (normals[:, i].astype(np.float32) for i in range(3))
    uv = mesh.uv if mesh.uv is not None else np.full((m, 3, 2), np.nan, np.float32)
    for v in range(3):
        cols[f"u{v}"] = uv[:, v, 0].astype(np.float32)
        cols[f"v{v}"] = uv[:, v, 1].astype(np.float32)
    tex = mesh.face_texture if mesh.face_texture is not None else np.full(m, -1, np.int16)
    cols["texture"] = tex.astype(np.int16)
    fc = mesh.face_colors if mesh.face_colors is not None else np.full((m, 3), 200, np.uint8)
    cols["red"], cols["green"], cols["blue"] = (fc[:, i].astype(np.uint8) for i in range(3))
    cols["src_face"] = np.arange(m, dtype=np.int64)
    cols["source"] = np.full(m, source, np.uint32)
    return cols


def to_campus(world: np.ndarray, frame: CampusFrame, matrix: np.ndarray | None, source: str) -> np.ndarray:
    """world (n, 3) float64 -> campus-local (n, 3) float64 (column-major), applying the registration when given.

    Patch cells are computed from this float64 result (``origin + local``, i.e. world coordinates), not
    from the float32 values stored, so a place keeps its patch whatever the origin; the cast to float32
    moves a point by at most ~0.1 mm within the checked reach. NaN/inf and points too far from the origin
    for float32 raise InputError naming ``source``.
    """
    world = np.asarray(world)
    n = len(world)
    d = [np.subtract(world[:, a], frame.origin_array[a], dtype=np.float64) for a in range(3)]  # contiguous columns
    if matrix is None:
        local = np.empty((n, 3), np.float64, order="F")
        for a in range(3):
            local[:, a] = d[a]
    else:  # per output axis, in place on contiguous columns: ~3x a (n, 3) @ (3, 3) on C-ordered rows
        m = np.asarray(matrix, np.float64)
        local = np.empty((n, 3), np.float64, order="F")
        for a in range(3):
            col = local[:, a]
            np.multiply(d[0], m[a, 0], out=col)
            col += m[a, 1] * d[1]
            col += m[a, 2] * d[2]
            col += m[a, 3]
    if n:
        lo = np.array([local[:, a].min() for a in range(3)])  # NaN propagates into both
        hi = np.array([local[:, a].max() for a in range(3)])
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            bad = int((~np.isfinite(local).all(axis=1)).sum())
            raise InputError(source, f"{bad} coordinates are NaN or infinite")
        reach = float(max(np.abs(lo[:2]).max(), np.abs(hi[:2]).max()))
        if reach > MAX_LOCAL_EXTENT_M * 5:
            raise InputError(source, f"coordinates lie {reach:,.0f} m from the campus origin {frame.origin}: wrong "
                                     "CRS, units or a mismatched extent (inputs must overlap the campus)")
    return local
