"""Compiled (numba) loops of the export's per-vertex work on a leaf's millions of faces.

- :func:`accumulate_face_normals`: area-weighted face normals summed onto their corners, in the order
  ``np.bincount`` summed them (face by face, corner by corner), so the same float64 sums;
- :func:`single_feature_vertices`: the common case of ``split_by_feature`` (no vertex shared by faces of
  different features) in one pass, without the (3m,) temporaries.

``benchmarks/kernel_bench.py`` times each against the numpy code it replaced. ``cache=True``: compiled once
per machine into ``__pycache__``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["accumulate_face_normals", "single_feature_vertices"]


@njit(cache=True, nogil=True)
def accumulate_face_normals(p: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n, 3) float64: for each vertex of ``p`` (n, 3) float64, the sum of the cross products
    (b - a) x (c - a) of the faces (m, 3) int using it (twice their area along their normal)."""
    acc = np.zeros((len(p), 3))
    for f in range(len(faces)):
        a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
        ux, uy, uz = p[b, 0] - p[a, 0], p[b, 1] - p[a, 1], p[b, 2] - p[a, 2]
        vx, vy, vz = p[c, 0] - p[a, 0], p[c, 1] - p[a, 1], p[c, 2] - p[a, 2]
        nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
        for k in range(3):
            v = faces[f, k]
            acc[v, 0] += nx
            acc[v, 1] += ny
            acc[v, 2] += nz
    return acc


@njit(cache=True, nogil=True)
def single_feature_vertices(faces: np.ndarray, feature: np.ndarray, n_vertices: int):
    """When no vertex of ``faces`` (m, 3) int64 is used by faces of different ``feature`` (m,) int64 >= 0:
    (True, new faces (m, 3) int64 over the used vertices renumbered in order, the source vertex (k,) int64
    and the feature (k,) int64 of each); else (False, empty arrays). n_vertices > every vertex id."""
    of_vertex = np.full(n_vertices, -1, np.int64)
    for f in range(len(faces)):
        for k in range(3):
            v = faces[f, k]
            if of_vertex[v] < 0:
                of_vertex[v] = feature[f]
            elif of_vertex[v] != feature[f]:
                e = np.zeros(0, np.int64)
                return False, np.zeros((0, 3), np.int64), e, e
    new_id = np.full(n_vertices, -1, np.int64)
    k = 0
    for v in range(n_vertices):
        if of_vertex[v] >= 0:
            new_id[v] = k
            k += 1
    src = np.empty(k, np.int64)
    fid = np.empty(k, np.int64)
    for v in range(n_vertices):
        if new_id[v] >= 0:
            src[new_id[v]] = v
            fid[new_id[v]] = of_vertex[v]
    out = np.empty((len(faces), 3), np.int64)
    for f in range(len(faces)):
        for j in range(3):
            out[f, j] = new_id[faces[f, j]]
    return True, out, src, fid
