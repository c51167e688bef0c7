"""The repair's real inputs to its two solvers, recorded on a synthetic campus (for cdt_bench.py and
maxflow_bench.py; not part of the package).

:func:`capture` generates a synth campus (``ms3d synth``), runs the whole pipeline on it in this process with
the 'inline' runner (``ms3d run --set runner=inline``) and records, while the repair runs,

- every chart the rebuild triangulates in its conformal map: the arguments of
  ``tasks.repair.conformal.constrained_triangles`` (uv (q, 2) float64, the boundary's length n_loop);
- every s-t graph it cuts: the arguments of ``tasks.repair.mincut.min_cut`` from the graph-cut fusion
  (``tasks.repair.fuse``) and from the view selection's expansion moves (``tasks.repair.views``).

The recording is saved as one pickle (``{"charts": [...], "graphs": [...], "preset", "seed", "seconds"}``)
and reused when it exists: the pipeline takes ~1.5 min on 'tiny', ~5 min on 'demo'.
"""

from __future__ import annotations

import argparse
import pickle
import shutil
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def capture(preset: str, seed: int, work: Path, out: Path | None = None) -> dict:
    """The recording of a pipeline run on the synth campus ``preset``/``seed`` under ``work`` (made there once,
    then read from ``out``, default ``work/capture.pkl``)."""
    out = out or work / "capture.pkl"
    if out.exists():
        return pickle.loads(out.read_bytes())
    import flows.cli
    import tasks.repair.conformal
    import tasks.repair.fuse
    import tasks.repair.mesh
    import tasks.repair.mincut
    import tasks.repair.views

    charts, graphs = [], []
    triangulate, cut = tasks.repair.conformal.constrained_triangles, tasks.repair.mincut.min_cut

    def recorded_triangles(uv, n_loop):
        charts.append({"uv": np.array(uv, np.float64), "n_loop": int(n_loop)})
        return triangulate(uv, n_loop)

    def recorded_cut(origin):
        def run(cap_source, cap_sink, a, b, cap, rev_cap, **kw):
            graphs.append({"origin": origin, "args": tuple(np.array(x) for x in (cap_source, cap_sink, a, b, cap,
                                                                                 rev_cap))})
            return cut(cap_source, cap_sink, a, b, cap, rev_cap, **kw)
        return run

    tasks.repair.mesh.constrained_triangles = recorded_triangles
    tasks.repair.fuse.min_cut = recorded_cut("fuse")
    tasks.repair.views.min_cut = recorded_cut("views")
    work.mkdir(parents=True, exist_ok=True)
    campus = work / "campus"
    synth = ["synth", "--preset", preset, "--seed", str(seed), "--out", str(campus), "--overwrite"]
    if not (campus / "campus.yaml").exists() and flows.cli.main(synth):
        raise SystemExit("ms3d synth failed")
    shutil.rmtree(work / "work", ignore_errors=True)  # a finished run would skip every region
    t0 = time.perf_counter()
    rc = flows.cli.main(["run", str(campus / "campus.yaml"), "--work-dir", str(work / "work"), "--set",
                         "runner=inline"])
    if rc and not (charts and graphs):
        raise SystemExit("ms3d run failed before the repair ran")
    if rc:  # a later stage failed: what the repair triangulated and cut is recorded all the same
        print("ms3d run failed after the repair: its charts and graphs are recorded", file=sys.stderr)
    rec = {"preset": preset, "seed": seed, "seconds": time.perf_counter() - t0, "charts": charts, "graphs": graphs}
    out.write_bytes(pickle.dumps(rec))
    return rec


def capture_parser(description: str, repeat: int) -> argparse.ArgumentParser:
    """The options every bench over a recorded repair shares: the campus (preset, seed), where the recording
    is kept, and how many timed repeats."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("--preset", default="tiny")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--work", type=Path, default=Path("/tmp/cdt-bench"))
    ap.add_argument("--repeat", type=int, default=repeat)
    return ap


def best_of(fn, repeat: int) -> tuple[float, object]:
    """(the least wall seconds of ``repeat`` calls of fn(), its result)."""
    best, res = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = fn()
        best = min(best, time.perf_counter() - t0)
    return best, res
