"""The constrained Delaunay of rebuilt charts: PythonCDT (what ms3d uses) against Shewchuk's Triangle (what it
used before; its notice forbids commercial distribution, so it is no dependency: measured only when installed),
side by side on the charts the repair triangulates on a synth campus.

    .venv/bin/python benchmarks/cdt_bench.py [--preset tiny] [--seed 1] [--work /tmp/cdt-bench] [--repeat 5]

The charts are recorded from a whole pipeline run (``benchmarks/_repair_capture.py``: every call of
``tasks.repair.conformal.constrained_triangles`` while the repair rebuilds the campus's regions; the recording
is kept in ``--work`` and reused, shared with ``maxflow_bench.py``). For each chart both backends get the same
points and boundary; the table prints, per backend, the best of ``--repeat`` wall times summed over the
charts, the triangles, the smallest angle, whether every boundary edge is an edge of the triangulation,
the charts refused (None: the caller falls back to the disc map), and the charts whose triangle sets are
identical (an unordered set of unordered triples; a tie between cocircular points may be broken either way).
The largest charts are listed one by one. Always exits 0: it reports.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import machine
from benchmarks._repair_capture import best_of, capture, capture_parser
from tasks.repair.conformal import constrained_triangles


def triangle_backend(uv: np.ndarray, n_loop: int) -> np.ndarray | None:
    """What ms3d called before: Triangle's constrained Delaunay of the planar straight-line graph ('p'),
    quiet ('Q'); None when it inserted a point or failed."""
    import triangle

    if len(uv) < 3:
        return np.zeros((0, 3), np.int64)
    seg = np.c_[np.arange(n_loop), np.roll(np.arange(n_loop), -1)]
    try:
        out = triangle.triangulate({"vertices": np.asarray(uv, np.float64), "segments": seg}, "pQ")
    except (RuntimeError, ValueError):
        return None
    if len(out.get("vertices", [])) != len(uv) or "triangles" not in out:
        return None
    return np.asarray(out["triangles"], np.int64)


def min_angle_deg(uv: np.ndarray, tri: np.ndarray) -> float:
    """The smallest interior angle of the triangles, degrees."""
    if len(tri) == 0:
        return float("nan")
    p = uv[tri]
    best = np.inf
    for k in range(3):
        u, v = p[:, (k + 1) % 3] - p[:, k], p[:, (k + 2) % 3] - p[:, k]
        cos = np.einsum("ij,ij->i", u, v) / np.maximum(np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1), 1e-300)
        best = min(best, float(np.degrees(np.arccos(np.clip(cos, -1, 1))).min()))
    return best


def boundary_kept(tri: np.ndarray, n_loop: int) -> bool:
    """Whether every boundary edge (i, i + 1 mod n_loop) is an edge of a triangle."""
    e = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    have = set(map(tuple, e.tolist()))
    i = np.arange(n_loop)
    want = np.sort(np.c_[i, (i + 1) % n_loop], axis=1)
    return all(tuple(w) in have for w in want.tolist())


def as_set(tri: np.ndarray) -> set:
    return set(map(tuple, np.sort(tri, axis=1).tolist()))


def main(argv: list[str] | None = None) -> int:
    ap = capture_parser(__doc__.split("\n\n")[0], repeat=5)
    ap.add_argument("--show", type=int, default=8, help="the largest charts listed one by one")
    args = ap.parse_args(argv)
    rec = capture(args.preset, args.seed, args.work / args.preset)
    charts = rec["charts"]
    backends = {"pythoncdt": constrained_triangles}
    try:
        import triangle  # noqa: F401

        backends["triangle"] = triangle_backend
    except ImportError:
        print("triangle not installed: PythonCDT alone (pip install triangle to compare)")
    print(f"{machine()}; {args.preset} campus (seed {args.seed}): {len(charts)} charts, "
          f"{sum(len(c['uv']) for c in charts)} points, largest {max((len(c['uv']) for c in charts), default=0)}")
    backends["pythoncdt"](np.array([[0.0, 0], [1, 0], [0, 1]]), 3)  # load the library once
    res = {name: [] for name in backends}
    for c in charts:
        for name, fn in backends.items():
            res[name].append(best_of(lambda fn=fn, c=c: fn(c["uv"], c["n_loop"]), args.repeat))
    print(f"\n{'backend':10} {'seconds':>9} {'triangles':>10} {'min angle':>10} {'boundary kept':>14} "
          f"{'refused':>8} {'same set':>9}")
    ref = res.get("triangle")
    for name, rows in res.items():
        done = [(c, t) for c, (_, t) in zip(charts, rows) if t is not None]
        kept = sum(boundary_kept(t, c["n_loop"]) for c, t in done)
        same = "" if ref is None else str(sum(
            a is not None and b is not None and as_set(a) == as_set(b) for (_, a), (_, b) in zip(rows, ref)))
        angle = min((min_angle_deg(c["uv"], t) for c, t in done if len(t)), default=float("nan"))
        print(f"{name:10} {sum(s for s, _ in rows):9.4f} {sum(len(t) for _, t in done):10d} {angle:10.4f} "
              f"{kept:>8d} of {len(done):<3d} {len(rows) - len(done):8d} {same:>9}")
    print(f"\nthe {args.show} largest charts: points, boundary, then per backend ms / triangles / min angle")
    for i in sorted(range(len(charts)), key=lambda i: -len(charts[i]["uv"]))[:args.show]:
        c = charts[i]
        cells = []
        for name, rows in res.items():
            s, t = rows[i]
            cells.append(f"{name} {s * 1e3:7.2f} ms " + ("refused" if t is None else
                                                          f"{len(t):6d} {min_angle_deg(c['uv'], t):7.3f}°"))
        print(f"{len(c['uv']):6d} {c['n_loop']:5d}   " + "   ".join(cells))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
