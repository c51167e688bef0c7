"""The repair's s-t min-cuts: ms3d's compiled Boykov–Kolmogorov (``tasks.repair.mincut``, backend 'bk') against
the GPL PyMaxflow wrapper it replaced (backend 'pymaxflow', the optional ``gpl`` extra: measured only when
installed) and, with ``--scipy``, SciPy's Dinic on integer-scaled capacities, side by side on the graphs the
repair cuts on a synth campus.

    .venv/bin/python benchmarks/maxflow_bench.py [--preset tiny] [--seed 1] [--work /tmp/cdt-bench] [--repeat 3]
        [--scipy] [--scale 1]

The graphs are recorded from a whole pipeline run (``benchmarks/_repair_capture.py``: every call of
``min_cut`` by the graph-cut fusion and by the view selection's expansion moves; the recording is kept in
``--work`` and reused, shared with ``cdt_bench.py``). ``--scale K`` adds K-times larger copies of the largest
fusion graph (K disjoint copies side by side: the size a real-density region reaches), to time the solvers
where the time goes.

Per backend and per origin (fuse / views): the best of ``--repeat`` wall times summed over the graphs (the
whole call: building the graph, the max flow, reading the cut), then, against 'bk': the graphs whose flow is
bitwise equal, those whose cut is the same to the node, and the largest relative difference of the cut's
energy (its value recomputed from the capacities in float64). SciPy's maximum_flow takes int32 capacities:
each graph is scaled so that its largest capacity is 2^30 / n, rounded, and its cut read from the residual
graph (the nodes that reach the sink). Always exits 0: it reports.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import machine
from benchmarks._repair_capture import best_of, capture, capture_parser
from tasks.repair.mincut import min_cut


def scipy_cut(cs, ct, a, b, cap, rev) -> tuple[float, np.ndarray]:
    """SciPy's Dinic on capacities scaled to int32: (flow in the input's units, (n,) bool sink side)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, maximum_flow

    n = len(cs)
    s, t = n, n + 1
    top = max(float(np.max(cs, initial=0)), float(np.max(ct, initial=0)), float(np.max(cap, initial=0)),
              float(np.max(rev, initial=0)), 1e-300)
    k = (1 << 30) / (top * max(n, 1))  # the summed capacities stay within int32
    nodes = np.arange(n)
    rows = np.concatenate([np.full(n, s), nodes, a, b])
    cols = np.concatenate([nodes, np.full(n, t), b, a])
    caps = np.rint(np.concatenate([cs, ct, cap, rev]) * k).astype(np.int64)
    keep = caps > 0
    c = coo_matrix((caps[keep].astype(np.int32), (rows[keep], cols[keep])), shape=(n + 2, n + 2)).tocsr()
    res = maximum_flow(c, s, t, method="dinic")
    resid = (c - res.flow).tocsr()  # residual u -> v: capacity minus (antisymmetric) flow
    resid.data = (resid.data > 0).astype(np.int8)
    resid.eliminate_zeros()
    reach = breadth_first_order(resid.T.tocsr(), t, directed=True, return_predecessors=False)
    sink = np.zeros(n + 2, bool)
    sink[reach] = True
    return res.flow_value / k, sink[:n]


def cut_energy(sink, cs, ct, a, b, cap, rev) -> float:
    return float(cs[sink].sum() + ct[~sink].sum() + cap[~sink[a] & sink[b]].sum() + rev[sink[a] & ~sink[b]].sum())


def copies(g: tuple, k: int) -> tuple:
    """k disjoint copies of the graph g side by side."""
    cs, ct, a, b, cap, rev = g
    n = len(cs)
    off = np.repeat(np.arange(k) * n, len(a))
    return (np.tile(cs, k), np.tile(ct, k), np.tile(a, k) + off, np.tile(b, k) + off, np.tile(cap, k),
            np.tile(rev, k))


def main(argv: list[str] | None = None) -> int:
    ap = capture_parser(__doc__.split("\n\n")[0], repeat=3)
    ap.add_argument("--scipy", action="store_true", help="also SciPy's Dinic on integer-scaled capacities")
    ap.add_argument("--scale", type=int, default=0, help="add the largest fusion graph K times over")
    args = ap.parse_args(argv)
    rec = capture(args.preset, args.seed, args.work / args.preset)
    graphs = [(g["origin"], tuple(np.asarray(x) for x in g["args"])) for g in rec["graphs"]]
    fuse = [g for o, g in graphs if o == "fuse"]
    if args.scale > 1 and fuse:
        graphs.append((f"fuse x{args.scale}", copies(max(fuse, key=lambda g: len(g[0])), args.scale)))
    backends = {"bk": lambda g: min_cut(*g)}
    try:
        import maxflow  # noqa: F401

        backends["pymaxflow"] = lambda g: min_cut(*g, backend="pymaxflow")
    except ImportError:
        print("PyMaxflow not installed: 'bk' alone (pip install 'ms3d[gpl]' to compare)")
    if args.scipy:
        backends["scipy"] = lambda g: scipy_cut(*g)
    one = (np.ones(2), np.ones(2), np.zeros(1, np.int64), np.ones(1, np.int64), np.ones(1), np.ones(1))
    warm, _ = best_of(lambda: min_cut(*one), 1)  # numba: load the cached machine code (or compile it)
    print(f"{machine()}; {args.preset} campus (seed {args.seed}): {len(graphs)} graphs, "
          f"largest {max((len(g[0]) for _, g in graphs), default=0)} nodes / "
          f"{max((len(g[2]) for _, g in graphs), default=0)} edges; bk's first call {warm:.2f} s (compiled code loaded)")
    res = {name: [best_of(lambda fn=fn, g=g: fn(g), args.repeat) for _, g in graphs] for name, fn in backends.items()}
    origins = sorted({o for o, _ in graphs})
    print(f"\n{'origin':10} {'graphs':>6} {'nodes':>9} {'edges':>9} {'backend':>10} {'seconds':>9} "
          f"{'same flow':>10} {'same cut':>9} {'max energy diff':>16}")
    for o in origins:
        idx = [i for i, (oo, _) in enumerate(graphs) if oo == o]
        nodes = sum(len(graphs[i][1][0]) for i in idx)
        edges = sum(len(graphs[i][1][2]) for i in idx)
        for name, rows in res.items():
            same_flow = sum(rows[i][1][0] == res["bk"][i][1][0] for i in idx)
            same_cut = sum(bool((rows[i][1][1] == res["bk"][i][1][1]).all()) for i in idx)
            diff = 0.0
            for i in idx:
                g = graphs[i][1]
                e0, e1 = cut_energy(res["bk"][i][1][1], *g), cut_energy(rows[i][1][1], *g)
                diff = max(diff, abs(e1 - e0) / max(abs(e0), 1e-12))
            print(f"{o:10} {len(idx):6d} {nodes:9d} {edges:9d} {name:>10} {sum(rows[i][0] for i in idx):9.4f} "
                  f"{same_flow:>5d} of {len(idx):<3d} {same_cut:>4d} of {len(idx):<3d} {diff:16.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
