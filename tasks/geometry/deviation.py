"""Signed scan-to-model distance per face: each scan point goes to the face nearest to it, and a face's value
is the mean signed distance of its points, positive where the scan lies in front of the face (on the side
its normal points to, i.e. the model lies behind the scan), negative behind.

    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0], [10, 0, 0], [14, 0, 0], [10, 4, 0]], float)
    >>> f = np.array([[0, 1, 2], [3, 4, 5]])  # normals +z
    >>> p = np.array([[1, 1, 0.02], [1, 1.5, 0.04], [11, 1, -0.05], [30, 0, 0]])
    >>> d, n = face_deviation(p, v, f, max_distance_m=0.25)
    >>> [round(float(x), 4) for x in d], n.tolist()
    ([0.03, -0.05], [2, 1])
"""

from __future__ import annotations

import numpy as np

from tasks.geometry.distance import MeshDistance
from tasks.geometry.triangles import face_normals


def face_deviation(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, max_distance_m: float = 0.25,
                   chunk_size: int = 1_000_000) -> tuple[np.ndarray, np.ndarray]:
    """Per face, the mean signed distance of the scan points nearest to it.

    points: (k, 3) float64 metres; vertices: (n, 3) float64, same frame; faces: (m, 3) int. Points farther
    than ``max_distance_m`` from every face (a car, a tree, a surface the model lacks) are left out.
    Returns ((m,) float32 metres, NaN for a face no point chose; (m,) int64 points per face).
    """
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    vertices = np.asarray(vertices, np.float64)
    total, count = np.zeros(len(faces)), np.zeros(len(faces), np.int64)
    if len(faces) and len(points):
        md = MeshDistance(vertices, faces)
        normals = face_normals(vertices, faces)
        for lo in range(0, len(points), chunk_size):
            p = np.asarray(points[lo:lo + chunk_size], np.float64)
            d, fid = md.query(p)
            ok = (fid >= 0) & (d <= max_distance_m)
            fid, d, p = fid[ok], d[ok], p[ok]
            side = np.einsum("ij,ij->i", p - vertices[faces[fid, 0]], normals[fid])
            total += np.bincount(fid, weights=np.where(side < 0, -d, d), minlength=len(faces))
            count += np.bincount(fid, minlength=len(faces))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / count, np.nan).astype(np.float32), count


__all__ = ["face_deviation"]
