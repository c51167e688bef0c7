"""Conforming split of long triangles, so a coarse mesh (city model LoD1/LoD2, CAD) reaches every patch
it crosses.

Faces go to the patch of their centroid (the paper's Algorithm 1). A city model's triangles are metres
long, so most patches a wall crosses would hold no face and could never be graded. Ingest therefore
splits every edge longer than ``max_edge_m`` (the smallest patch side) before binning.

**Rule** (rounds of edge bisection, decided per edge): in each round every edge longer than
``max_edge_m`` gets its midpoint, and each face is re-triangulated by the pattern of its split edges:
one split edge -> 2 faces (midpoint to the opposite corner), two -> 3 (the corner triangle, and the
remaining quad cut along its shorter diagonal), three -> 4 (the midpoint triangle). Rounds repeat until
no edge is longer than ``max_edge_m`` (or ``max_rounds``).

- *Conforming* (no T-junctions): whether an edge is split depends only on its two end points, which both
  faces sharing it hold bitwise-identically, and a midpoint is ``(a + b) * 0.5`` (commutative in IEEE
  arithmetic), so both faces create the same point in every round.
- *Vertex ids*: a midpoint's id is a hash of its edge's two end-point ids (taken in sorted order), so the
  two faces sharing the edge give it the SAME id, and recursive midpoints follow. Ids of original
  vertices are ``source << 32 | index`` >= 0 (``source`` < 2**31, :mod:`storage.inputs.identity`) and -1 means
  "no id", so new ids live in the reserved range ``[-2**62 - 1, -2]``: they cannot collide with an
  original id. Two different edges share a new id with probability ~ n**2 / 2**63 for n new vertices
  (about 1e-3 at 1e8 new vertices).
- Per-face attributes are kept: each piece records its ``parent`` face (normal, texture, colour and
  ``src_face`` follow it) and corner uvs are interpolated linearly, so texture mapping is unchanged.
- The pieces tile the parent exactly (area conserved up to rounding) and keep its winding.

**Cost**: a face of area A becomes about ``A / (0.2 * max_edge_m**2)`` pieces (right-isosceles halves of
an edge of ``max_edge_m``): a 10 m x 3 m wall quad (2 faces) becomes ~300 faces at 0.7 m; an MVS mesh
(edges ~0.15 m) is left almost untouched. Time and memory are linear in the output, one vectorised pass
per round (~log2(longest edge / max_edge_m) rounds).

**Guarantee**: every piece has edges <= ``max_edge_m``, so its centroid lies within
``max_edge_m / sqrt(3)`` of every point of it: a patch whose part of the surface contains a disk of
that radius holds at least one piece.

    >>> import numpy as np
    >>> tri = np.array([[[0., 0, 0], [2, 0, 0], [1, 0.5, 0]]])
    >>> s = split_long_faces(tri, np.array([[0, 1, 2]]), max_edge_m=1.5)
    >>> len(s.tri), s.parent.tolist(), bool((s.ids[0] == [0, 1, 2]).any())
    (2, [0, 0], True)
    >>> int(split_vertex_id(np.array([0]), np.array([1]))[0]) == int(split_vertex_id(np.array([1]), np.array([0]))[0])
    True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_ROUNDS = 40  # 2**40 x max_edge_m: far beyond any input

# pieces of a face by pattern, as corner triples into (A, B, C, M0, M1, M2), M_k the midpoint of edge k
# (edge k runs from corner k to corner k+1); faces are rotated first so the pattern is one of these
_ONE = np.array([[0, 3, 2], [3, 1, 2]])                    # edge 0 split
_TWO_A = np.array([[3, 1, 4], [0, 3, 4], [0, 4, 2]])       # edges 0, 1 split; quad cut along A-M1
_TWO_B = np.array([[3, 1, 4], [0, 3, 2], [3, 4, 2]])       # edges 0, 1 split; quad cut along M0-C
_THREE = np.array([[0, 3, 5], [3, 1, 4], [5, 4, 2], [3, 4, 5]])


@dataclass(frozen=True)
class SplitFaces:
    """The pieces: tri (k, 3, 3) float64 corners (same frame as the input); ids (k, 3) int64 vertex ids;
    uv (k, 3, 2) float32 or None; parent (k,) int64 index of the input face each piece comes from.
    Unsplit faces come first, in input order, followed by the pieces of split faces."""

    tri: np.ndarray
    ids: np.ndarray
    uv: np.ndarray | None
    parent: np.ndarray

    @property
    def n_split(self) -> int:
        """How many input faces were split."""
        return int(np.count_nonzero(np.bincount(self.parent) > 1))


def _mix(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser on uint64 (wrapping arithmetic)."""
    x = x ^ (x >> np.uint64(30))
    x = x * np.uint64(0xBF58476D1CE4E5B9)
    x = x ^ (x >> np.uint64(27))
    x = x * np.uint64(0x94D049BB133111EB)
    return x ^ (x >> np.uint64(31))


def split_vertex_id(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Id of the midpoint of edge (a, b): (k,) int64 ids -> (k,) int64 in ``[-2**62 - 1, -2]``.

    Symmetric (``f(a, b) == f(b, a)``) and deterministic; never >= -1, so never an input vertex id.
    """
    lo = np.minimum(a, b).astype(np.int64).view(np.uint64)
    hi = np.maximum(a, b).astype(np.int64).view(np.uint64)
    with np.errstate(over="ignore"):
        h = _mix(_mix(lo + np.uint64(0x9E3779B97F4A7C15)) ^ hi)
    return np.int64(-2) - (h >> np.uint64(2)).astype(np.int64)


def _edge_lengths(tri: np.ndarray) -> np.ndarray:
    """(k, 3, 3) -> (k, 3): length of edge j = corner j -> corner j+1 (symmetric in its end points)."""
    d = tri[:, [1, 2, 0]] - tri
    return np.sqrt(np.einsum("kij,kij->ki", d, d))


def _split_round(tri, ids, uv, parent, split):
    """One round on faces with at least one split edge: (tri, ids, uv, parent) of their pieces."""
    count = split.sum(axis=1)
    first = np.argmax(split, axis=1)  # count 1: the split edge
    unsplit = np.argmin(split, axis=1)  # count 2: the edge left whole
    shift = np.where(count == 1, first, np.where(count == 2, (unsplit - 2) % 3, 0))
    rot = (np.arange(3)[None, :] + shift[:, None]) % 3  # new corner c = old corner rot[c]
    rows = np.arange(len(tri))[:, None]
    t, i = tri[rows, rot], ids[rows, rot]
    nxt = [1, 2, 0]
    pts = np.concatenate([t, (t + t[:, nxt]) * 0.5], axis=1)  # (k, 6, 3): A, B, C, M0, M1, M2
    pid = np.concatenate([i, split_vertex_id(i, i[:, nxt])], axis=1)
    puv = None
    if uv is not None:
        u = uv[rows, rot]
        puv = np.concatenate([u, ((u.astype(np.float64) + u[:, nxt]) * 0.5).astype(np.float32)], axis=1)
    diag_a = np.linalg.norm(pts[:, 0] - pts[:, 4], axis=1) <= np.linalg.norm(pts[:, 3] - pts[:, 2], axis=1)
    out_t, out_i, out_u, out_p = [], [], [], []
    for sel, tmpl in ((count == 1, _ONE), ((count == 2) & diag_a, _TWO_A), ((count == 2) & ~diag_a, _TWO_B),
                      (count == 3, _THREE)):
        k = np.flatnonzero(sel)
        if len(k) == 0:
            continue
        out_t.append(pts[k[:, None, None], tmpl[None]].reshape(-1, 3, 3))
        out_i.append(pid[k[:, None, None], tmpl[None]].reshape(-1, 3))
        if puv is not None:
            out_u.append(puv[k[:, None, None], tmpl[None]].reshape(-1, 3, 2))
        out_p.append(np.repeat(parent[k], len(tmpl)))
    return (np.concatenate(out_t), np.concatenate(out_i), np.concatenate(out_u) if puv is not None else None,
            np.concatenate(out_p))


def split_long_faces(tri: np.ndarray, ids: np.ndarray, max_edge_m: float, uv: np.ndarray | None = None,
                     max_rounds: int = MAX_ROUNDS) -> SplitFaces:
    """Split every edge longer than ``max_edge_m`` until none is (the module's rule; conforming).

    tri: (m, 3, 3) float64 corners, metres (any Cartesian frame; faces sharing an edge must hold its end
    points bitwise-identically, as corners gathered from one vertex array do); ids: (m, 3) int64 vertex
    ids, equal for equal corners; uv: (m, 3, 2) per-corner texture coordinates or None.
    """
    if not max_edge_m > 0:
        raise ValueError(f"max_edge_m must be positive, got {max_edge_m}")
    tri = np.asarray(tri, np.float64)
    ids = np.asarray(ids, np.int64)
    parent = np.arange(len(tri), dtype=np.int64)
    done_t, done_i, done_u, done_p = [], [], [], []
    for _ in range(max_rounds + 1):
        split = _edge_lengths(tri) > max_edge_m
        whole = ~split.any(axis=1)
        done_t.append(tri[whole])
        done_i.append(ids[whole])
        done_p.append(parent[whole])
        if uv is not None:
            done_u.append(uv[whole])
        if whole.all():
            break
        tri, ids, uv, parent = _split_round(tri[~whole], ids[~whole], None if uv is None else uv[~whole],
                                            parent[~whole], split[~whole])
    else:  # max_rounds reached: keep what is left as it is
        done_t.append(tri)
        done_i.append(ids)
        done_p.append(parent)
        if uv is not None:
            done_u.append(uv)
    return SplitFaces(np.concatenate(done_t), np.concatenate(done_i),
                      np.concatenate(done_u) if uv is not None else None, np.concatenate(done_p))


__all__ = ["MAX_ROUNDS", "SplitFaces", "split_long_faces", "split_vertex_id"]
