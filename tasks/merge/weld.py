"""Welding kernels of the merge stage: face soups keyed by vertex id -> one indexed mesh.

A *face soup* gives each face corner a weld key (int64; the campus vertex id of the patch store, or a
key of a rebuilt region's own vertex) and its attributes (uv, texture, colour). Welding gives each key
one vertex, splits a key into several vertices only where its corners disagree on texture, uv or
colour (texture seams), drops degenerate faces (two corners on one key) and duplicate faces (the same
three keys in any order or orientation; the first one in soup order is kept). Nothing here compares
positions: faces that share an edge share the two keys (``storage.patches``: weld by id, not by
position), so the result is exact, and float noise can never open or close a seam.

Everything is vectorised: one stable argsort of the keys, one of the packed face keys, and a lexsort
over the corners of seam vertices only (typically a few per cent of the corners).

    >>> keys = np.array([[10, 11, 12], [12, 11, 13], [11, 10, 12], [13, 13, 10]])
    >>> keep = face_keep_mask(weld_keys(keys.reshape(-1))[0], n_faces=4)
    >>> keep.tolist()   # face 2 repeats face 0 reversed, face 3 is degenerate
    [True, True, False, False]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.geometry.groups import first_of_groups

_PACK_BITS = 21  # three vertex numbers below 2**21 pack into one int64 face key


def weld_keys(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Number the distinct keys in ascending order.

    keys: (c,) int64. Returns (kid (c,) int64 in [0, k): the key's rank; first (k,) int64: the index of
    each key's first occurrence in ``keys``; order (c,) int64: the stable argsort of ``keys``).

    >>> kid, first, _ = weld_keys(np.array([7, 3, 7, 5]))
    >>> kid.tolist(), first.tolist()
    ([2, 0, 2, 1], [1, 3, 0])
    """
    keys = np.asarray(keys, np.int64).reshape(-1)
    if len(keys) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    order = np.argsort(keys, kind="stable")  # stable: the first of equal keys is its first occurrence
    sk = keys[order]
    new = np.empty(len(keys), bool)
    new[0] = True
    np.not_equal(sk[1:], sk[:-1], out=new[1:])
    del sk
    kid = np.empty(len(keys), np.int64)
    kid[order] = np.cumsum(new) - 1
    return kid, order[new], order


def face_keep_mask(kid: np.ndarray, n_faces: int) -> np.ndarray:
    """(m,) bool: faces that are neither degenerate nor a repeat of an earlier face.

    kid: (3 m,) int64 vertex numbers of the face corners (from :func:`weld_keys`), face-major.
    A repeat is a face with the same three vertices in any order (so either orientation): two faces
    on the same three vertices are one surface drawn twice.
    """
    f = np.sort(np.asarray(kid, np.int64).reshape(n_faces, 3), axis=1)
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2])
    if n_faces == 0:
        return np.zeros(0, bool)
    if f.max() < (1 << _PACK_BITS):
        packed = (f[:, 0] << (2 * _PACK_BITS)) | (f[:, 1] << _PACK_BITS) | f[:, 2]
        first = weld_keys(packed)[1]
    else:
        _, first = first_of_groups(f[:, 0], f[:, 1], f[:, 2])
    keep = np.zeros(n_faces, bool)
    keep[first] = True
    return keep & ~degenerate


@dataclass(frozen=True, eq=False)
class WeldResult:
    """An indexed mesh out of a face soup.

    faces: (m, 3) int32 vertex indices. corner: (n,) int64, for each vertex the soup corner (face-major
    index into the 3 m kept corners) whose attributes it takes. position_corner: (n,) int64, the corner
    whose position it takes: the first corner of its key in soup order, so every vertex split from one
    key sits at exactly one position (seams stay closed). n_keys: distinct keys; n_split: vertices
    added at seams (n = n_keys + n_split).
    """

    faces: np.ndarray
    corner: np.ndarray
    position_corner: np.ndarray
    n_keys: int
    n_split: int


def weld_corners(keys: np.ndarray, attr_a: np.ndarray, attr_b: np.ndarray,
                 welded: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None, attrs_sorted: bool = False
                 ) -> WeldResult:
    """Weld face corners by key, splitting a key where its corners' attributes differ.

    keys: (3 m,) int64 weld key per corner, face-major (the faces already deduplicated).
    attr_a, attr_b: (3 m,) int64 attributes that must agree for two corners to share a vertex (the
    merge packs texture + colour into one and the uv bits into the other).
    welded: ``weld_keys(keys)`` when the caller has it already. attrs_sorted: attr_a and attr_b are given
    in key-sorted order already (``attr[order]``, ``order`` from ``welded``), so the caller can free the
    unsorted ones before the kernel's own arrays exist (the merge's peak).

    Vertices 0 .. k-1 are the keys in ascending order (each takes its first corner's attributes);
    split vertices follow, in key order. Seam corners are matched to the first earlier corner of their
    key with equal attributes by a vectorised scan over the key's corners (in key-sorted order, a
    pass per position in the group: passes = the largest valence, each over the corners still open),
    which is a few times faster than a lexsort of all corners when most corners are seam corners.

    >>> k = np.array([1, 2, 3, 3, 2, 4])              # two faces sharing the edge 2-3
    >>> a = np.zeros(6, np.int64); b = np.array([0, 0, 0, 9, 0, 0])  # corner 3 of face 1: other uv
    >>> w = weld_corners(k, a, b)
    >>> w.faces.tolist(), w.n_split
    ([[0, 1, 2], [4, 1, 3]], 1)
    """
    kid, first, order = weld_keys(keys) if welded is None else welded
    n_keys, c = len(first), len(kid)
    idx = np.int32 if c < 2**31 else np.int64  # positions in sorted order: half the bytes at the peak
    # in key-sorted order: sa/sb the attributes, start the position where each corner's key begins
    sa, sb = (attr_a, attr_b) if attrs_sorted else (attr_a[order], attr_b[order])
    new = np.zeros(c, bool)
    new[np.searchsorted(kid[order], np.arange(n_keys))] = True
    start = np.maximum.accumulate(np.where(new, np.arange(c, dtype=idx), idx(0)))
    match = start.copy()  # position (sorted order) of the first corner with equal key and attributes
    open_ = np.flatnonzero((sa != sa[start]) | (sb != sb[start])).astype(idx)
    match[open_] = open_  # until an earlier equal corner is found: a vertex of its own
    d = 1
    while len(open_):
        ahead = start[open_] + idx(d)
        live = ahead < open_  # candidates strictly before the corner itself
        open_, ahead = open_[live], ahead[live]
        hit = (sa[open_] == sa[ahead]) & (sb[open_] == sb[ahead])
        match[open_[hit]] = ahead[hit]
        open_ = open_[~hit]
        d += 1
    del sa, sb, start
    is_extra = (match == np.arange(c, dtype=idx)) & ~new  # first corners of split vertices
    number = np.empty(c, np.int64)
    number[new] = np.arange(n_keys)
    number[is_extra] = n_keys + np.arange(int(is_extra.sum()))
    vert = np.empty(c, np.int64)
    vert[order] = number[match]
    del number, match
    corner = np.concatenate([first, order[is_extra]])
    position_corner = first[kid[corner]]
    return WeldResult(vert.reshape(-1, 3).astype(np.int32), corner, position_corner, n_keys, len(corner) - n_keys)
