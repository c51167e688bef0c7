"""Vertices split so that no vertex is shared by faces of different features (a glTF vertex carries one
feature id, one uv). Pure."""

from __future__ import annotations

import numpy as np


def split_by_feature(faces: np.ndarray, feature: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compact the vertices of ``faces`` so that no vertex is shared by faces of different features.

    faces: (m, 3) int; feature: (m,) int >= 0. Returns (new faces (m, 3) int64, source vertex per new
    vertex (k,) int64, feature per new vertex (k,) int64); new vertices ordered by (source, feature).

    >>> f, src, fid = split_by_feature(np.array([[0, 1, 2], [2, 1, 3]]), np.array([0, 1]))
    >>> f.tolist(), src.tolist(), fid.tolist()
    ([[0, 1, 3], [4, 2, 5]], [0, 1, 1, 2, 2, 3], [0, 0, 1, 0, 1, 1])
    """
    faces = np.asarray(faces, np.int64)
    if len(faces) == 0:
        return faces.reshape(0, 3), np.zeros(0, np.int64), np.zeros(0, np.int64)
    single = _single_feature_split(faces, np.asarray(feature, np.int64))
    if single is not None:
        return single
    n_feat = int(feature.max()) + 1
    key = (faces * n_feat + np.asarray(feature, np.int64)[:, None]).reshape(-1)
    space = (int(faces.max()) + 1) * n_feat
    if space <= 4 * key.size:  # a dense table: linear time, no sort (sized by the faces, not the vertex ids)
        used = np.zeros(space, bool)
        used[key] = True
        uniq = np.flatnonzero(used)
        new_id = np.cumsum(used, dtype=np.int64 if space >= 1 << 31 else np.int32) - 1
        inverse = new_id[key].astype(np.int64)
    else:
        uniq, inverse = np.unique(key, return_inverse=True)
    return inverse.reshape(-1, 3), uniq // n_feat, uniq % n_feat


def _single_feature_split(faces: np.ndarray, feature: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """:func:`split_by_feature` in linear time when no vertex is shared by faces of different features (the
    common case: merged tiles split their vertices at texture seams); None otherwise."""
    corners = faces.reshape(-1)
    if int(corners.max()) + 1 > 4 * corners.size:  # a table sized by the vertex ids would cost more than a sort
        return None
    corner_feature = np.repeat(feature, 3)
    of_vertex = np.full(int(corners.max()) + 1, -1, np.int64)
    of_vertex[corners] = corner_feature
    if (of_vertex[corners] != corner_feature).any():
        return None
    used = of_vertex >= 0
    new_id = np.cumsum(used) - 1
    src = np.flatnonzero(used)
    return new_id[faces], src, of_vertex[src]
