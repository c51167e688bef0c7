"""``make demo`` / ``ms3d demo``: generate the demo campus, run the pipeline embedded, say where things are."""

from __future__ import annotations

import json
import time
from pathlib import Path


def _has_campus(out: Path, preset: str, seed: int) -> bool:
    m = out / "truth" / "manifest.json"
    if not m.exists():
        return False
    doc = json.loads(m.read_text())
    return doc.get("preset") == preset and doc.get("seed") == seed and all((out / f).exists() for f in doc["files"])


def run_demo(out: Path, work: Path, seed: int = 7, preset: str = "demo") -> int:
    from flows.campus import CampusRunFailed, run_campus
    from flows.runtime import PrefectServer, embedded_prefect
    from flows.status import campus_status, format_status
    from flows.summary import format_summary
    from storage.workdir.layout import WorkDir
    from synth.generate import generate
    from tasks.classify import DEFAULT_MODEL_TRAINING_SEEDS
    from tasks.config import CampusConfig

    out, work = out.absolute(), work.absolute()
    t0 = time.perf_counter()
    prefect_dir = WorkDir(work).prefect_dir
    server = PrefectServer(prefect_dir).launch()  # it starts (~10 s) while the campus is generated
    try:
        if _has_campus(out, preset, seed):
            print(f"[1/3] demo campus already generated in {out}")
        else:
            print(f"[1/3] generating the '{preset}' campus (seed {seed}) in {out} ...", flush=True)
            generate(preset, seed=seed, out=out, overwrite=True)
            print(f"      done in {time.perf_counter() - t0:.0f} s")
        cfg = CampusConfig.from_yaml(out / "campus.yaml", {"work_dir": str(work)})
    except BaseException:  # the server must not outlive a failed generation
        server.stop()
        raise
    print(f"[2/3] running the pipeline (embedded Prefect server + local Dask cluster) into {work} ...", flush=True)
    t1 = time.perf_counter()
    try:
        with embedded_prefect(prefect_dir, launched=server):
            summary = run_campus(cfg, progress=True)
        rc = 0
    except CampusRunFailed as e:
        print(str(e))
        rc = 1
        summary = None
    print(f"      done in {time.perf_counter() - t1:.0f} s")
    if summary:
        print("      " + format_summary(summary).replace("\n", "\n      "))
    if summary:
        print(f"      orchestration: sum of task times {summary['task_seconds']:.0f} s against flow wall time "
              f"{summary['wall_seconds']:.0f} s on {cfg.cluster.n_workers} workers "
              f"(parallel efficiency {summary['task_seconds'] / summary['wall_seconds'] / cfg.cluster.n_workers:.0%})")
    print("[3/3] quality of the model against the truth (from the run report):", flush=True)
    if seed in DEFAULT_MODEL_TRAINING_SEEDS.get(preset, ()) and not cfg.classify.model:
        print(f"      (seed {seed} is one of the shipped grader's training campuses: these figures are in-sample; "
              "held-out figures: docs/benchmarks.md)")
    print(_quality_lines(work))
    print()
    print(format_status(campus_status(str(work))))
    if summary:
        print(f"\ninputs:        {out}\nwork dir:      {work}\npatch stores:  {work / 'tiles'}/<tile>/*.parquet"
              f"\n3D Tiles:      {work / 'output' / 'tileset.json'}\nrun report:    {work / 'output' / 'report.html'}"
              f"\nview it:       ms3d view {work}   (then open the printed localhost address)"
              f"\nrun history:   ms3d ui {work}")
    return rc


def _quality_lines(work: Path) -> str:
    path = work / "report" / "quality.json"
    try:
        rows = json.loads(path.read_text())["rows"]
    except (OSError, ValueError, KeyError):
        return "      (no quality figures: the report could not measure the model)"
    lines = []
    for name, q in rows.items():
        lines.append(f"      {name:<14} F-score {q['fscore'][0]:.3f} at 5 cm, {q['fscore'][1]:.3f} at 10 cm; accuracy mean "
                     f"{100 * q['accuracy']['mean_m']:.1f} cm, completeness mean {100 * q['completeness']['mean_m']:.1f} cm; "
                     f"{100 * q['uncovered_fraction']:.1f} % of the true facade area uncovered")
        for cls, c in (q.get("per_class") or {}).items():
            if cls in ("wall", "glass", "frame", "balcony"):
                lines.append(f"        {cls:<8} F@5cm {c['fscore'][0]:.2f}")
    return "\n".join(lines)
