"""Per-face quantities of a triangle mesh: unit normals and areas.

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


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """vertices: (n, 3) float64 metres; faces: (m, 3) int64 -> (m,) float64 m²."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


__all__ = ["face_areas", "face_normals"]
