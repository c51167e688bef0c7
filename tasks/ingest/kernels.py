"""Ingest's pure kernels: the campus frame transform, welded vertex ids (with tile seams of a production
welded across files), and the staging columns of points and faces. Arrays in, arrays out; no I/O here.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from storage.contracts.staging import FACE_VERTEX_COLUMNS
from storage.errors import InputError
from storage.formats.meshes import MeshData
from storage.formats.points import PointChunk
from storage.frame import MAX_LOCAL_EXTENT_M, CampusFrame
from storage.inputs.identity import VERTEX_INDEX_BITS
from tasks.geometry.split import split_long_faces


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


SEAM_ID_BIT = 1 << 31  # set in the low word of a seam id; ordinary vertex indices stay below it


def open_boundary_vertices(faces: np.ndarray, canonical: np.ndarray) -> np.ndarray:
    """Which vertices lie on an open edge (an edge of exactly one face), edges taken over welded indices.

    faces: (m, 3) int vertex indices; canonical: (n,) int64 from :func:`weld_vertex_index` -> (n,) bool,
    True for every vertex (welded or not) at the position of an open-edge corner.

    >>> bool(open_boundary_vertices(np.array([[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]]), np.arange(4)).any())
    False
    >>> open_boundary_vertices(np.array([[0, 1, 2], [0, 2, 3]]), np.arange(5)).tolist()
    [True, True, True, True, False]
    """
    n = len(canonical)
    if len(faces) == 0:
        return np.zeros(n, bool)
    f = canonical[np.asarray(faces)]
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    on_open = np.zeros(n, bool)
    on_open[uniq[counts == 1].ravel()] = True
    return on_open[canonical]


def _mix64(z: np.ndarray) -> np.ndarray:
    """The splitmix64 finaliser: a bijective avalanche of uint64 values (arithmetic wraps mod 2**64)."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def seam_ids(world: np.ndarray, production_key: int) -> np.ndarray:
    """Vertex ids of tile-seam vertices: a 62-bit hash of the production key and the exact float64 bits
    of the world position, laid out as ``hi31 << 32 | SEAM_ID_BIT | lo31``.

    world: (k, 3) float64 metres (after offset and units scale) -> (k,) int64 >= 0. Every tile of a
    production computes the same id for the same position from its own file alone; the ids never equal
    an ordinary ``source << 32 | index`` id (whose bit 31 is clear), and two different seam positions of
    one campus share an id with probability ~k_total**2 / 2**63 (1e-5 for ten million seam vertices).
    -0.0 and 0.0 are one position.

    >>> a = seam_ids(np.array([[589000.25, 2712000.5, 15.0], [0.0, -0.0, 1.0]]), 7)
    >>> b = seam_ids(np.array([[589000.25, 2712000.5, 15.0], [-0.0, 0.0, 1.0]]), 7)
    >>> bool((a == b).all() and (a & SEAM_ID_BIT).all() and (a >= 0).all() and a[0] != a[1])
    True
    """
    bits = (np.ascontiguousarray(world, np.float64) + 0.0).view(np.uint64).reshape(-1, 3)
    with np.errstate(over="ignore"):
        h = _mix64(np.full(len(bits), production_key & ((1 << 64) - 1), np.uint64))
        for a in range(3):
            h = _mix64(h ^ bits[:, a])
    hi = h >> np.uint64(33)  # 31 bits
    lo = h & np.uint64(SEAM_ID_BIT - 1)  # 31 bits
    return ((hi << np.uint64(32)) | np.uint64(SEAM_ID_BIT) | lo).astype(np.int64)


def vertex_ids(source: int, faces: np.ndarray, canonical: np.ndarray, vertices: np.ndarray | None = None,
               seam_key: int | None = None) -> np.ndarray:
    """Campus-unique vertex ids per face corner. faces: (m, 3) int -> (m, 3) int64.

    An ordinary file: ``source << 32 | canonical vertex index`` (canonical: (n,) int64 from
    :func:`weld_vertex_index`, < 2**31). A tile of a production (``seam_key``: its
    :func:`storage.formats.production.production_key`; vertices: (n, 3) float64 world metres): the same, except
    that vertices on an open edge of the tile, where its neighbours join, get :func:`seam_ids` of their
    world position, so the coincident border vertices of adjacent tiles share one id.
    """
    if len(canonical) and canonical.max() >= SEAM_ID_BIT:
        raise ValueError("a mesh file with more than 2**31 vertices")
    ids = (np.int64(source) << VERTEX_INDEX_BITS) | canonical.astype(np.int64)
    if seam_key is not None and len(canonical):
        border = open_boundary_vertices(faces, canonical)
        ids[border] = seam_ids(np.asarray(vertices, np.float64)[border], seam_key)
    return ids[faces]


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


def split_mesh_faces(mesh: MeshData, tri64: np.ndarray, vids: np.ndarray,
                     max_edge_m: float) -> tuple[MeshData, np.ndarray, np.ndarray, np.ndarray]:
    """Faces longer than ``max_edge_m`` split (:mod:`tasks.geometry.split`: conforming, shared-edge ids).

    tri64: (m, 3, 3) float64 campus-local corners; vids: (m, 3) int64. Returns (the mesh's per-face
    attributes for the k pieces: uv interpolated, texture and colours of the parent face; tri (k, 3, 3)
    float64; vids (k, 3) int64; parent (k,) int64 input face of each piece).
    """
    s = split_long_faces(tri64, vids, max_edge_m, uv=mesh.uv)
    if len(s.parent) == len(tri64):  # nothing split: keep the file's face order
        return mesh, tri64, vids, np.arange(len(tri64), dtype=np.int64)
    return replace(mesh.select_faces(s.parent), uv=s.uv), s.tri, s.ids, s.parent


def face_columns(mesh: MeshData, tri_local: np.ndarray, vids: np.ndarray, normals: np.ndarray,
                 source: int, src_face: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Staging/patch-store face columns.

    tri_local: (m, 3, 3) float32 campus-local metres; vids: (m, 3) int64 vertex ids; normals: (m, 3) unit;
    src_face: (m,) int64 face index in the input file (default: row order).
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
    cols["src_face"] = np.arange(m, dtype=np.int64) if src_face is None else src_face.astype(np.int64)
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
