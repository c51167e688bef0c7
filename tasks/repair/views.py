"""Seam-aware view labels for the faces of a rebuilt mesh: alpha-expansion over s-t min-cuts
(:func:`tasks.repair.mincut.min_cut`).

The data costs are sparse: a camera sees a small part of a region (on the demo's largest region, 777 k
candidate (face, view) pairs of 203 k faces x 51 labels, 7.5 %), so they are kept as (face, label, cost)
entries and each move touches only the faces that may take its label and the edges around them. The
labels, moves and energies are those of the dense formulation (the same graphs, built in the same order:
tests compare both).
"""

from __future__ import annotations

import numpy as np

from tasks.repair.mincut import min_cut


def _unary(cost0: np.ndarray, cost1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(source, sink) capacities of the unary costs of x=0 (source side) and x=1 (sink side), less their
    minimum."""
    m = np.minimum(cost0, cost1)
    return cost1 - m, cost0 - m


class _Incidence:
    """The edges (rows of the adjacency) around a set of faces, in edge order."""

    def __init__(self, a: np.ndarray, b: np.ndarray, m: int) -> None:
        ends = np.concatenate([a, b])
        order = np.argsort(ends, kind="stable")
        self.edge = np.concatenate([np.arange(len(a)), np.arange(len(b))])[order]
        self.start = np.searchsorted(ends[order], np.arange(m + 1))

    def around(self, faces: np.ndarray) -> np.ndarray:
        lo, hi = self.start[faces], self.start[faces + 1]
        n = hi - lo
        if not n.sum():
            return np.zeros(0, np.int64)
        idx = np.repeat(lo - np.concatenate([[0], np.cumsum(n)[:-1]]), n) + np.arange(n.sum())
        return np.unique(self.edge[idx])


def _expansion_move(cur: np.ndarray, lab: np.ndarray, alpha: int, faces: np.ndarray, cost: np.ndarray,
                    edges: np.ndarray, a: np.ndarray, b: np.ndarray, w: np.ndarray, node: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """One alpha-expansion move: (labels, per-face costs) after the faces that lower the energy most switch
    to ``alpha``.

    cur: (m,) cost of each face's current label; faces, cost: the faces that allow ``alpha`` (ascending)
    and their cost of it; edges: the adjacency rows around them (ascending); (a, b, w): (e,) adjacent face
    pairs and their Potts weights; node: (m,) int64 scratch, -1 everywhere (left so). Only faces that may
    switch are graph nodes; an edge to a face that keeps its label becomes a unary term of the other end
    (its cost if it keeps vs if it switches), which is exact: the fixed end's variable is 0 in every cut."""
    sel = lab[faces] != alpha
    cand = faces[sel]
    nc = len(cand)
    if nc == 0:
        return lab, cur
    node[cand] = np.arange(nc)
    ea, eb, we = a[edges], b[edges], w[edges]
    fa, fb = node[ea] >= 0, node[eb] >= 0
    la, lb = lab[ea], lab[eb]
    e00 = we * (la != lb)
    e01 = we * (la != alpha)  # a keeps, b switches
    e10 = we * (lb != alpha)  # a switches, b keeps
    keep = cur[cand].astype(np.float64)
    switch = cost[sel].astype(np.float64)
    one_a, one_b = fa & ~fb, fb & ~fa  # an edge to a face that keeps: a unary term of its candidate end
    keep += np.bincount(node[ea[one_a]], e00[one_a], nc) + np.bincount(node[eb[one_b]], e00[one_b], nc)
    switch += np.bincount(node[ea[one_a]], e10[one_a], nc) + np.bincount(node[eb[one_b]], e01[one_b], nc)
    both = fa & fb
    na, nb = node[ea[both]], node[eb[both]]
    e00, e01, e10 = e00[both], e01[both], e10[both]
    # E = e00 + (e10 - e00) x_a + (0 - e10) x_b + (e01 + e10 - e00) (1 - x_a) x_b
    switch += np.bincount(na, e10 - e00, nc) + np.bincount(nb, -e10, nc)
    node[cand] = -1
    cap_source, cap_sink = _unary(keep, switch)  # x = 1 (sink): switch to alpha; x = 0 (source): keep
    _, moved = min_cut(cap_source, cap_sink, na, nb, np.maximum(e01 + e10 - e00, 0), np.zeros(len(na)))
    new, new_cur = lab.copy(), cur.copy()
    new[cand[moved]] = alpha
    new_cur[cand[moved]] = cost[sel][moved]
    return new, new_cur


def select_views_sparse(m: int, face: np.ndarray, label: np.ndarray, cost: np.ndarray, adjacency: np.ndarray,
                        seam_weight, cycles: int = 3) -> np.ndarray:
    """Seam-aware view labels: argmin sum_f cost(f, l_f) + sum_{(f, g) adjacent, l_f != l_g} seam_weight_fg,
    over the labels each face allows.

    m: faces; face, label, cost: (k,) the allowed (face, label) pairs and their finite costs (every face
    needs at least one: the texture step's 'no view' label); adjacency: (e, 2) face pairs; seam_weight: a
    scalar or (e,) per adjacent pair. Alpha-expansion (Boykov, Veksler & Zabih 2001): for each label
    alpha, one s-t min-cut decides which faces switch to alpha; Potts is a metric, so each move is exact.
    Starts from each face's cheapest label (the lowest label on a tie). Returns (m,) int64 labels.
    """
    face, label = np.asarray(face, np.int64), np.asarray(label, np.int64)
    cost = np.asarray(cost, np.float64)
    first = np.lexsort((label, cost, face))
    head = first[np.r_[True, face[first][1:] != face[first][:-1]]] if len(first) else first
    if len(head) != m or (len(head) and (face[head] != np.arange(m)).any()):
        raise ValueError("every face needs at least one allowed label")
    lab, cur = label[head].copy(), cost[head].copy()
    w = np.broadcast_to(np.asarray(seam_weight, np.float64), (len(adjacency),))
    labels = np.unique(label)
    if len(adjacency) == 0 or not (w > 0).any() or len(labels) == 1:
        return lab
    a, b = adjacency[:, 0], adjacency[:, 1]
    by_label = np.lexsort((face, label))
    bounds = np.searchsorted(label[by_label], np.r_[labels, labels[-1] + 1])
    inc = _Incidence(a, b, m)
    columns = []  # per label: its faces (ascending), their costs, the edges around them
    for i in range(len(labels)):
        rows = by_label[bounds[i]:bounds[i + 1]]
        columns.append((face[rows], cost[rows], inc.around(face[rows])))
    node = np.full(m, -1, np.int64)

    def energy(lb, cu):
        return cu.sum() + w[lb[a] != lb[b]].sum()

    best = energy(lab, cur)
    for _ in range(cycles):
        improved = False
        for alpha, (faces, col, edges) in zip(labels.tolist(), columns):
            new, new_cur = _expansion_move(cur, lab, alpha, faces, col, edges, a, b, w, node)
            en = energy(new, new_cur)
            if en < best - 1e-9:
                best, lab, cur, improved = en, new, new_cur, True
        if not improved:
            break
    return lab


def select_views(cost: np.ndarray, adjacency: np.ndarray, seam_weight, cycles: int = 3) -> np.ndarray:
    """:func:`select_views_sparse` of a dense (m, L) float64 cost matrix, np.inf where a label is not
    allowed (every face must allow at least one). Returns (m,) int64 labels."""
    face, label = np.nonzero(np.isfinite(cost))
    return select_views_sparse(len(cost), face, label, cost[face, label], adjacency, seam_weight, cycles)
