"""A clean mesh made to look like a real production's structure: node borders, cracks, slivers, seams.

Real photogrammetric productions are not watertight (``../shared/REAL_DATA.md``): they are split into tiles
and level-of-detail nodes whose borders leave open edges and hairline cracks, texture charts duplicate the
vertices along their seams, and triangulation leaves slivers and the odd duplicated face. None of this is a
defect: the surface is where it should be. :func:`crack_production` adds exactly that structure to a clean
mesh (the synth truth), so a test can hold the grader to "a clean, non-watertight mesh with a scan that
agrees with it is good".

- nodes: faces grouped by centroid in ``node_m`` squares (xy); each node owns its vertex copies, so node
  borders are open edges;
- cracks: each node's border vertices moved by up to ``crack_m`` in a random direction (no weld reunites
  them; a hairline, far below any defect);
- seams: inside a node, faces grouped again by ``chart_m`` squares get their own vertex copies too (texture
  charts split at their seams: duplicated vertices, open edges after an exact weld fails nowhere);
- slivers: a ``sliver_share`` of faces split at a point ``sliver_t`` along one edge into a sliver and a
  near-whole triangle (a T-vertex: one more open edge);
- duplicates: a ``duplicate_share`` of faces repeated (non-manifold edges).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CrackParams:
    """Sizes (metres) and shares of :func:`crack_production`."""

    node_m: float = 12.0
    chart_m: float = 4.0
    crack_m: float = 0.003
    sliver_share: float = 0.02
    sliver_t: float = 0.02
    duplicate_share: float = 0.002


def _split_by_groups(v: np.ndarray, f: np.ndarray, group: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertex copies per group: (vertices (n', 3), faces (m, 3), vertex group (n',)). A vertex used by faces
    of k groups appears k times."""
    corner_group = np.repeat(group, 3)
    key = f.ravel().astype(np.int64) * (int(group.max()) + 1) + corner_group
    uniq, inv = np.unique(key, return_inverse=True)
    src = uniq // (int(group.max()) + 1)
    return v[src], inv.reshape(-1, 3).astype(np.int64), uniq % (int(group.max()) + 1)


def _cells(c: np.ndarray, size: float) -> np.ndarray:
    """(m,) int64 id of the xy square of side ``size`` of each centroid (m, 3)."""
    ij = np.floor(c[:, :2] / size).astype(np.int64)
    ij -= ij.min(axis=0)
    return ij[:, 0] * (int(ij[:, 1].max()) + 1) + ij[:, 1]


def crack_production(rng: np.random.Generator, vertices: np.ndarray, faces: np.ndarray,
                     p: CrackParams | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The same surface with a production's structure: (vertices (n', 3) float64, faces (m', 3) int64).

    vertices (n, 3) metres, faces (m, 3); the input is not modified. Every output face lies on an input
    face, except that crack vertices move by at most ``crack_m``."""
    p = p or CrackParams()
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    c = v[f].mean(axis=1)
    node = _cells(c, p.node_m)
    v, f, vnode = _split_by_groups(v, f, node)
    # a border vertex: its position is shared with another node's copy
    _, pos_inv, pos_count = np.unique(np.round(v, 6), axis=0, return_inverse=True, return_counts=True)
    border = pos_count[pos_inv.ravel()] > 1
    d = rng.normal(size=(int(border.sum()), 3))
    d *= (rng.uniform(0.3, 1.0, len(d)) * p.crack_m / np.linalg.norm(d, axis=1))[:, None]
    v = v.copy()
    v[border] += d
    chart = node * 1_000_003 + _cells(c, p.chart_m)
    _, chart = np.unique(chart, return_inverse=True)
    v, f, _ = _split_by_groups(v, f, chart.ravel())
    m = len(f)
    pick = np.flatnonzero(rng.random(m) < p.sliver_share)
    if len(pick):  # split edge (a, b) of face (a, b, c) at a + t (b - a): faces (a, s, c) and (s, b, c)
        a, b, cc = f[pick, 0], f[pick, 1], f[pick, 2]
        s = len(v) + np.arange(len(pick))
        v = np.concatenate([v, v[a] + p.sliver_t * (v[b] - v[a])])
        f = f.copy()
        f[pick] = np.stack([a, s, cc], axis=1)
        f = np.concatenate([f, np.stack([s, b, cc], axis=1)])
    dup = np.flatnonzero(rng.random(len(f)) < p.duplicate_share)
    return v, np.concatenate([f, f[dup]])


def open_edge_share(faces: np.ndarray, vertices: np.ndarray | None = None, decimals: int = 6) -> float:
    """Share of the undirected edges used by one face only, after welding vertices that coincide to
    ``decimals`` (the way a production's edges are counted: "x % stay open after welding")."""
    f = np.asarray(faces, np.int64)
    if vertices is not None:
        _, inv = np.unique(np.round(np.asarray(vertices), decimals), axis=0, return_inverse=True)
        f = inv.ravel()[f]
    e = np.sort(np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return float((counts == 1).mean())


__all__ = ["CrackParams", "crack_production", "open_edge_share"]
