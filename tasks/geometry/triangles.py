"""Per-face and per-vertex quantities of a triangle mesh: unit face normals, face areas, vertex normals.

Vertices are (n, 3) float64 metres in any Cartesian frame; faces are (m, 3) integer vertex indices,
corners in winding order.

    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [1, 0, 0]], float)
    >>> f = np.array([[0, 1, 2], [0, 3, 1]])
    >>> face_normals(v, f).tolist(), face_areas(v, f).tolist()
    ([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]], [2.0, 0.0])
"""

from __future__ import annotations

import numpy as np


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (right hand on corners 0 -> 1 -> 2). vertices: (n, 3) float64; faces: (m, 3) int
    -> (m, 3) float64 (zero for a degenerate face)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def face_areas(vertices: np.ndarray, faces: np.ndarray, dtype=None) -> np.ndarray:
    """vertices: (n, 3) float64 metres; faces: (m, 3) int64 -> (m,) m², computed in the vertices' dtype, or
    in ``dtype`` (e.g. ``np.float64`` for float32 vertices)."""
    v = vertices if dtype is None else np.asarray(vertices, dtype)
    a, b, c = (v[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


VERTEX_SUM_ORDERS = ("faces", "corners", "corner_sums")


def _corner_sums(faces: np.ndarray, cross: np.ndarray, n: int, order: str) -> np.ndarray:
    """(n, 3) sums of the (m, 3) face vectors ``cross`` at each face's three corners, in ``order``."""
    acc = np.zeros((n, 3))
    if order == "corner_sums":
        for d in range(3):
            acc[:, d] = sum(np.bincount(faces[:, k], weights=cross[:, d], minlength=n) for k in range(3))
        return acc
    corners = faces.reshape(-1) if order == "faces" else faces.T.reshape(-1)
    for d in range(3):
        w = np.repeat(cross[:, d], 3) if order == "faces" else np.tile(cross[:, d], 3)
        acc[:, d] = np.bincount(corners, weights=w, minlength=n)
    return acc


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, *, stored_normals: np.ndarray | None = None,
                   order: str = "faces", eps: float = 0.0, undefined=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Area-weighted unit vertex normals: each face's edge cross product (its normal times twice its area)
    summed at its three corners, normalised. vertices: (n, 3); faces: (m, 3) int -> (n, 3) float64.

    stored_normals: (m, 3) unit face normals to use instead of the corners' own direction where finite
    (still weighted by the face's area). Where a vertex's sum has a norm <= ``eps`` it gets ``undefined``;
    ``undefined=None`` divides those sums by ``eps`` instead (a zero sum stays zero).

    order: the summation order of a vertex's faces, which decides the last bits (float addition is not
    associative); each caller keeps the order its outputs were made with. "faces": face by face, a face's
    corners in turn (the export); "corners": every face's first corner, then second, then third (repair);
    "corner_sums": the three per-corner sums added (synth).

    >>> v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 5, 5]], float)
    >>> vertex_normals(v, np.array([[0, 1, 2]])).tolist()
    [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    >>> vertex_normals(v, np.array([[0, 1, 2]]), undefined=(0.0, 1.0, 0.0))[3].tolist()
    [0.0, 1.0, 0.0]
    """
    if order not in VERTEX_SUM_ORDERS:
        raise ValueError(f"order must be one of {VERTEX_SUM_ORDERS}, not {order!r}")
    v = np.asarray(vertices, np.float64)
    cross = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    if stored_normals is not None:  # stored normals are computed in float64 world: keep their direction
        area2 = np.linalg.norm(cross, axis=1, keepdims=True)
        fn = np.nan_to_num(np.asarray(stored_normals, np.float64))
        cross = np.where(np.isfinite(stored_normals).all(1, keepdims=True), fn * area2, cross)
    acc = _corner_sums(faces, cross, len(v), order)
    norm = np.linalg.norm(acc, axis=1, keepdims=True)
    unit = acc / np.maximum(norm, max(eps, 1e-30))  # 1e-30: never a division by a subnormal norm
    return unit if undefined is None else np.where(norm > eps, unit, undefined)


__all__ = ["VERTEX_SUM_ORDERS", "face_areas", "face_normals", "vertex_normals"]
