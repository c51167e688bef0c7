"""Exact s-t minimum cuts of the repair's graphs (the graph-cut fusion, the view selection's expansion moves):
a compiled (numba) Boykov–Kolmogorov max-flow in float64.

The algorithm is the one of Boykov & Kolmogorov, "An experimental comparison of min-cut/max-flow
algorithms for energy minimization in vision" (PAMI 2004): a search tree grown from the source and one from
the sink meet on an augmenting path; after the augmentation the nodes cut off from their tree (orphans)
look for a new parent in the same tree or become free, and growth resumes from the active nodes. Written
for ms3d from the paper; it visits nodes and arcs in the order the authors' C++ library does (a node's arcs
newest first, the active nodes first in, first out, the orphans of an augmentation newest first, each
followed by the orphans it leaves), so the float sums, the flow and the cut are the same as with the GPL
PyMaxflow wrapper of that library: ``benchmarks/maxflow_bench.py`` and ``tests/tasks/repair/test_mincut.py``
compare both on the repair's graphs (bitwise equal flows, the same cut to the node).

A node is on the sink side when it ends in the sink tree (it reaches the sink through unsaturated arcs), on
the source side otherwise, free nodes included: of all the minimum cuts, the one with the smallest sink side.

:func:`min_cut` takes the graph as arrays: per node its source and sink capacities, per edge (a, b) its
capacities a -> b and b -> a; all float64 >= 0. The first call in a process loads the compiled code from
``__pycache__`` (or compiles it, ~3 s, on a machine's first run).
"""

from __future__ import annotations

import numpy as np
from numba import njit

_NONE, _TERMINAL, _ORPHAN = -1, -2, -3
_INF_D = 1 << 40


@njit(cache=True, nogil=True, inline="always")
def _activate(i, q, qnext):
    """Append node ``i`` to the active queue (``q``: [head, tail], -1 when empty; ``qnext[tail] == tail``)."""
    if q[1] >= 0:
        qnext[q[1]] = i
    else:
        q[0] = i
    q[1] = i
    qnext[i] = i


@njit(cache=True, nogil=True)
def _init_trees(tr_cap):
    """The two trees' roots: every node with residual source (sink) capacity is a child of the source
    (sink), active in node order. Returns (parent, is_sink, ts, dist, qnext, q): parent arc per node (or
    _NONE, _TERMINAL, _ORPHAN), its tree, its time stamp and distance to the terminal (the heuristics of
    the paper), and the active list (qnext[j] -1: not active, j: the last one; q: [first, last])."""
    n = len(tr_cap)
    parent = np.full(n, _NONE, np.int64)
    is_sink = np.zeros(n, np.bool_)
    ts = np.zeros(n, np.int64)
    dist = np.zeros(n, np.int64)
    qnext = np.full(n, -1, np.int64)
    q = np.full(2, -1, np.int64)
    for i in range(n):
        if tr_cap[i] > 0 or tr_cap[i] < 0:
            is_sink[i] = tr_cap[i] < 0
            parent[i] = _TERMINAL
            dist[i] = 1
            _activate(i, q, qnext)
    return parent, is_sink, ts, dist, qnext, q


@njit(cache=True, nogil=True, inline="always")
def _adopt(orphans, n_orph, time, first, nxt, head, rcap, parent, is_sink, ts, dist, qnext, q, fifo):
    """Each orphan of an augmentation (newest first), then the orphans it leaves, first in first out: the
    nearest parent in its own tree whose path reaches the terminal without an orphan, else free (its tree
    neighbours become active again, its children orphans)."""
    for oi in range(n_orph - 1, -1, -1):
        f_head, f_tail = 0, 1
        fifo[0] = orphans[oi]
        while f_head < f_tail:
            o = fifo[f_head]
            f_head += 1
            sink = is_sink[o]
            best, d_min = -1, _INF_D
            a0 = first[o]
            while a0 >= 0:
                if (rcap[a0] if sink else rcap[a0 ^ 1]) != 0.0:
                    j = head[a0]
                    if is_sink[j] == sink and parent[j] != _NONE:
                        d = 0  # the origin of j: a terminal (a tree path), or an orphan
                        while True:
                            if ts[j] == time:
                                d += dist[j]
                                break
                            e = parent[j]
                            d += 1
                            if e == _TERMINAL:
                                ts[j] = time
                                dist[j] = 1
                                break
                            if e == _ORPHAN:
                                d = _INF_D
                                break
                            j = head[e]
                        if d < _INF_D:
                            if d < d_min:
                                best, d_min = a0, d
                            j = head[a0]  # mark the path checked: its distances for this time
                            while ts[j] != time:
                                ts[j] = time
                                dist[j] = d
                                d -= 1
                                j = head[parent[j]]
                a0 = nxt[a0]
            if best >= 0:
                parent[o] = best
                ts[o] = time
                dist[o] = d_min + 1
                continue
            parent[o] = _NONE
            a0 = first[o]
            while a0 >= 0:
                j = head[a0]
                e = parent[j]
                if is_sink[j] == sink and e != _NONE:
                    if (rcap[a0] if sink else rcap[a0 ^ 1]) != 0.0 and qnext[j] < 0:
                        _activate(j, q, qnext)
                    if e != _TERMINAL and e != _ORPHAN and head[e] == o:
                        parent[j] = _ORPHAN
                        fifo[f_tail] = j
                        f_tail += 1
                a0 = nxt[a0]


@njit(cache=True, nogil=True)
def _bk(tr_cap, first, nxt, head, rcap, flow):
    """Max flow of the residual graph (tr_cap: (n,) source minus sink residual of each node; arcs in
    (first, nxt) lists, head, rcap: (2e,) with arc ^ 1 its sister), changed in place; flow: the flow through
    both terminals already. Returns (max flow, parent, is_sink)."""
    n = len(tr_cap)
    parent, is_sink, ts, dist, qnext, q = _init_trees(tr_cap)
    orphans, fifo = np.empty(n, np.int64), np.empty(n + 1, np.int64)
    time, current = 0, -1
    while True:
        i = current
        if i >= 0:
            qnext[i] = -1
            if parent[i] == _NONE:
                i = -1
        while i < 0 and q[0] >= 0:  # the next active node still in a tree
            i = q[0]
            q[0] = qnext[i] if qnext[i] != i else -1
            q[1] = q[1] if q[0] >= 0 else -1
            qnext[i] = -1
            i = i if parent[i] != _NONE else -1
        if i < 0:
            break
        mid, sink = -1, is_sink[i]  # growth over i's unsaturated arcs, up to an arc into the other tree
        a = first[i]
        while a >= 0:
            if (rcap[a ^ 1] if sink else rcap[a]) != 0.0:
                j = head[a]
                if parent[j] == _NONE:
                    is_sink[j], parent[j], ts[j], dist[j] = sink, a ^ 1, ts[i], dist[i] + 1
                    if qnext[j] < 0:
                        if q[1] >= 0:
                            qnext[q[1]] = j
                        else:
                            q[0] = j
                        q[1], qnext[j] = j, j
                elif is_sink[j] != sink:
                    mid = a ^ 1 if sink else a
                    break
                elif ts[j] <= ts[i] and dist[j] > dist[i]:  # a shorter path to the terminal through i
                    parent[j], ts[j], dist[j] = a ^ 1, ts[i], dist[i] + 1
            a = nxt[a]
        time += 1
        if mid < 0:
            current = -1
            continue
        qnext[i], current = i, i  # i stays active without a place in the list: it grows again next
        bottle, k = rcap[mid], head[mid ^ 1]  # the bottleneck of source root -> mid -> sink root
        while parent[k] != _TERMINAL:
            bottle, k = min(bottle, rcap[parent[k] ^ 1]), head[parent[k]]
        bottle, k = min(bottle, tr_cap[k]), head[mid]
        while parent[k] != _TERMINAL:
            bottle, k = min(bottle, rcap[parent[k]]), head[parent[k]]
        bottle = min(bottle, -tr_cap[k])
        rcap[mid ^ 1] += bottle
        rcap[mid] -= bottle
        n_orph = 0
        for side in range(2):  # 0: the source tree's path (the flow goes parent -> child), 1: the sink's
            k = head[mid ^ 1] if side == 0 else head[mid]
            while parent[k] != _TERMINAL:
                e = parent[k]
                down = e ^ 1 if side == 0 else e  # the arc the flow goes along
                rcap[down ^ 1] += bottle
                rcap[down] -= bottle
                if rcap[down] == 0.0:
                    parent[k], orphans[n_orph], n_orph = _ORPHAN, k, n_orph + 1
                k = head[e]
            tr_cap[k] += -bottle if side == 0 else bottle
            if tr_cap[k] == 0.0:
                parent[k], orphans[n_orph], n_orph = _ORPHAN, k, n_orph + 1
        flow += bottle
        _adopt(orphans, n_orph, time, first, nxt, head, rcap, parent, is_sink, ts, dist, qnext, q, fifo)
    return flow, parent, is_sink


@njit(cache=True, nogil=True)
def _arc_lists(n, a, b, cap, rev):
    """Arcs 2k: a[k] -> b[k] (cap), 2k + 1: b[k] -> a[k] (rev), each node's arcs newest first."""
    m = len(a)
    first = np.full(n, -1, np.int64)
    nxt = np.empty(2 * m, np.int64)
    head = np.empty(2 * m, np.int64)
    rcap = np.empty(2 * m, np.float64)
    for k in range(m):
        i, j = a[k], b[k]
        head[2 * k], head[2 * k + 1] = j, i
        rcap[2 * k], rcap[2 * k + 1] = cap[k], rev[k]
        nxt[2 * k] = first[i]
        first[i] = 2 * k
        nxt[2 * k + 1] = first[j]
        first[j] = 2 * k + 1
    return first, nxt, head, rcap


@njit(cache=True, nogil=True)
def _terminals(cap_source, cap_sink):
    """(n,) residual source minus sink capacity of each node, and the flow through both terminals."""
    n = len(cap_source)
    tr = np.empty(n, np.float64)
    flow = 0.0
    for i in range(n):
        cs, ct = cap_source[i], cap_sink[i]
        flow += min(ct, cs)
        tr[i] = cs - ct
    return tr, flow


def _min_cut_pymaxflow(cs, ct, a, b, cap, rev):
    try:
        import maxflow
    except ImportError:
        raise ImportError("min_cut backend 'pymaxflow' needs PyMaxflow (GPL), which is not installed: "
                          "pip install 'ms3d[gpl]', or use the default backend 'bk'") from None
    n = len(cs)
    g = maxflow.Graph[float](n, len(a))
    nodes = g.add_nodes(n)
    g.add_grid_tedges(nodes, cs, ct)
    if len(a):
        g.add_edges(np.asarray(a, np.int32), np.asarray(b, np.int32), cap, rev)
    flow = g.maxflow()
    return float(flow), np.asarray(g.get_grid_segments(nodes), bool)


def min_cut(cap_source: np.ndarray, cap_sink: np.ndarray, a: np.ndarray, b: np.ndarray, cap: np.ndarray,
            rev_cap: np.ndarray, backend: str = "bk") -> tuple[float, np.ndarray]:
    """Minimum s-t cut of a graph of n nodes: ``(max flow, (n,) bool sink side)``.

    cap_source, cap_sink: (n,) float64 >= 0, a node's arc from the source (paid when it lands on the sink
    side) and to the sink (paid on the source side); a, b: (e,) int node pairs (a != b); cap, rev_cap: (e,)
    float64 >= 0 capacities a -> b (paid when a is on the source side and b on the sink side) and b -> a.
    The cut's value (the sum of the capacities it pays) equals the returned flow.
    backend: "bk" (this module) or "pymaxflow" (the GPL PyMaxflow wrapper, the optional ``gpl`` extra; for
    comparisons).

    >>> flow, sink = min_cut(np.array([3.0, 0.0]), np.array([0.0, 2.0]), np.array([0]), np.array([1]),
    ...                      np.array([1.0]), np.array([0.0]))
    >>> flow, sink.tolist()
    (1.0, [False, True])
    """
    cs = np.ascontiguousarray(cap_source, np.float64)
    ct = np.ascontiguousarray(cap_sink, np.float64)
    n = len(cs)
    if n == 0:
        return 0.0, np.zeros(0, bool)
    if backend == "pymaxflow":
        return _min_cut_pymaxflow(cs, ct, a, b, np.asarray(cap, np.float64), np.asarray(rev_cap, np.float64))
    if backend != "bk":
        raise ValueError(f"unknown min_cut backend {backend!r}: 'bk' or 'pymaxflow'")
    tr, flow = _terminals(cs, ct)
    first, nxt, head, rcap = _arc_lists(n, np.ascontiguousarray(a, np.int64), np.ascontiguousarray(b, np.int64),
                                        np.ascontiguousarray(cap, np.float64),
                                        np.ascontiguousarray(rev_cap, np.float64))
    flow, parent, is_sink = _bk(tr, first, nxt, head, rcap, flow)
    return float(flow), (parent != _NONE) & is_sink


__all__ = ["min_cut"]
