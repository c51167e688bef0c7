"""Real meshes: no harm on a good one, repair of a defective one, per checkpoint, with the synth beside.

    .venv/bin/python benchmarks/real_mesh_bench.py [--sources sceaux,ccstreet] [--work-root DIR]
        [--models default,geo] [--defect-seeds 2] [--synth WORK_DIR ...]

The cases (:mod:`benchmarks.real_cases`, one per real source: the Sceaux castle MVS mesh scaled to metres in
EPSG:2154, and a ContextCapture 3MXB street corner, each with an MLS ray-cast from it along a street) are
built once and reused while their keys hold. Each checkpoint runs the
whole pipeline inline (``--set runner=inline``, ``classify.model`` set for the non-default ones) in its own
work dir. Figures per checkpoint:

- graded patches (grade good or bad in ``tiles/*/grades.parquet``; unknown apart) and the bad share;
- F@5cm, precision and recall of the merged model against the input mesh: the run's own
  ``report/quality.json`` (``tasks.quality``: both surfaces sampled every 10 cm, exact point-to-mesh
  distances, 25 m quality tiles with distances capped at their 2 m buffer), the case's truth being the
  input mesh itself;
- the merged model's surface area against the input's (sum of triangle areas of the welded merged tiles
  and of the input as ingest stored it), and the share of merged area that repair rebuilt.

The no-harm goal on a zero-defect case: <= 3 % bad, F@5cm >= 0.98, area within +-3 %.

Defect cases (:mod:`benchmarks.real_defects`, one per ``--defect-seeds`` seed: the zero case's truth and
scan, the mesh with labelled injected defects) print, per checkpoint: bad recall / precision of the shipped
grades against the labels, and F@5cm and uncovered area of the input mesh and of the merged model against
the truth, with the classes (ground, wall, roof) the merged model does worse on. The goal there: ms3d beats
the input on F@5cm and on uncovered area with no class worse.

``--synth W ...``: processed, labelled synth work dirs (never used for a choice) scored with ``ms3d evaluate``
per checkpoint (the model alone and the shipped path): mean [min, max] of AP, precision and recall on bad.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_cases import SOURCES, build_zero_defect
from real_defects import build_defect_case

from storage.contracts.tile_mesh import SOURCE_REBUILT, read_tile_mesh
from storage.workdir.layout import WorkDir
from tasks.geometry.triangles import face_areas
from tasks.quality.stage import ingested_surface, merged_tiles

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "ms3d_model" / "weights"
MODELS = {"default": None, "geo": WEIGHTS / "ms3dqe_geo.pt", "ms3dqe": WEIGHTS / "ms3dqe.pt",
          "plus": WEIGHTS / "ms3dqe_plus.pt"}
GOAL = {"bad_share": 0.03, "f5": 0.98, "area_change": 0.03}


def run_pipeline(case: Path, work: Path, model: Path | None, log: Path, extra: tuple[str, ...] = ()) -> float:
    """``ms3d run`` on the case into ``work`` (inline runner); seconds. The log keeps its output."""
    cmd = [str(ROOT / ".venv" / "bin" / "ms3d"), "run", str(case / "campus.yaml"), "--work-dir", str(work),
           "--set", "runner=inline"]
    if model is not None:
        cmd += ["--set", f"classify.model={model}"]
    for kv in extra:
        cmd += ["--set", kv]
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        r = subprocess.run(cmd, check=False, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(f"ms3d run failed ({r.returncode}); see {log}")
    return time.perf_counter() - t0


def grade_counts(work: Path) -> dict:
    """Patches by grade over every tile: good, bad, unknown; graded = good + bad."""
    grades = np.concatenate([pd.read_parquet(p, columns=["grade"])["grade"].to_numpy()
                             for p in sorted((work / "tiles").glob("*/grades.parquet"))])
    good, bad = int((grades == 0).sum()), int((grades == 1).sum())
    return {"graded": good + bad, "good": good, "bad": bad, "unknown": int((grades < 0).sum()),
            "bad_share": bad / max(1, good + bad)}


def areas(work: Path) -> dict:
    """Surface area (m^2) of the input as ingested and of the merged model, and the rebuilt share."""
    wd = WorkDir(work)
    tiles = merged_tiles(wd)
    v, f = ingested_surface(wd, tiles, np.zeros(3))
    a_in = float(face_areas(v, f, np.float64).sum())
    a_out = a_rebuilt = 0.0
    for k in tiles:
        tm = read_tile_mesh(work / "tiles" / k)
        fa = face_areas(tm.vertices, tm.faces.astype(np.int64), np.float64)
        a_out += float(fa.sum())
        a_rebuilt += float(fa[tm.source == SOURCE_REBUILT].sum())
    return {"area_in_m2": a_in, "area_out_m2": a_out, "area_change": a_out / a_in - 1.0,
            "rebuilt_area_share": a_rebuilt / max(a_out, 1e-9)}


def quality(work: Path) -> dict:
    """F@5cm, precision, recall of the merged model against the truth (= the input mesh) from the run."""
    path = work / "report" / "quality.json"
    if not path.exists():
        return {"f5": float("nan"), "p5": float("nan"), "r5": float("nan")}
    row = json.loads(path.read_text())["rows"]["merged model"]
    i = row["taus_m"].index(0.05)
    return {"f5": row["fscore"][i], "p5": row["precision"][i], "r5": row["recall"][i],
            "acc_p95_m": row["accuracy"]["p95_m"], "acc_max_m": row["accuracy"]["max_m"]}


def bench_model(case: Path, work_root: Path, name: str, force: bool, extra: tuple[str, ...] = ()) -> dict:
    """One checkpoint's row. ``ms3d run`` skips what its manifest says is done, so a repeat is quick; ``force``
    starts from an empty work dir."""
    work = work_root / (f"work-{name}" + "".join(f"-{kv.replace('=', '_')}" for kv in extra))
    if force and work.exists():
        shutil.rmtree(work)
    work_root.mkdir(parents=True, exist_ok=True)
    seconds = run_pipeline(case, work, MODELS[name], work.with_suffix(".log"), extra)
    row = {"checkpoint": name, "sets": list(extra), "model": str(MODELS[name] or "default (ms3d_model/weights/default.pt)"),
           **grade_counts(work), **quality(work), **areas(work), "run_s": seconds}
    row["meets_goal"] = bool(row["bad_share"] <= GOAL["bad_share"] and row["f5"] >= GOAL["f5"]
                             and abs(row["area_change"]) <= GOAL["area_change"])
    return row


def labelled_grades(work: Path) -> dict:
    """Bad recall / precision of the stored grades (the shipped path) against the labels, over patches with
    both: {"labelled_bad", "flagged", "recall_bad", "precision_bad"}."""
    tp = fp = fn = 0
    for td in sorted((work / "tiles").glob("*/grades.parquet")):
        g = pd.read_parquet(td, columns=["patch", "grade"])
        lab = td.parent / "labels.parquet"
        if not lab.exists():
            continue
        m = g.merge(pd.read_parquet(lab, columns=["patch", "label"]), on="patch")
        m = m[(m["grade"] >= 0) & (m["label"] >= 0)]
        tp += int(((m["grade"] == 1) & (m["label"] == 1)).sum())
        fp += int(((m["grade"] == 1) & (m["label"] == 0)).sum())
        fn += int(((m["grade"] == 0) & (m["label"] == 1)).sum())
    return {"labelled_bad": tp + fn, "flagged": tp + fp, "recall_bad": tp / max(1, tp + fn),
            "precision_bad": tp / max(1, tp + fp)}


def input_vs_merged(work: Path) -> dict:
    """F@5cm and uncovered area (m^2) of the input mesh and the merged model against the truth, and the
    classes whose F@5cm or uncovered area the merged model makes worse."""
    rows = json.loads((work / "report" / "quality.json").read_text())["rows"]
    out, worse = {}, []
    for name, key in (("input mesh", "in"), ("merged model", "out")):
        r = rows[name]
        out[f"f5_{key}"] = r["fscore"][r["taus_m"].index(0.05)]
        out[f"uncovered_{key}_m2"] = r["uncovered_area_m2"]
    for c, ri in rows["input mesh"]["per_class"].items():
        ro = rows["merged model"]["per_class"].get(c)
        if ro and (ro["fscore"][0] < ri["fscore"][0] - 1e-3 or ro["uncovered_area_m2"] > ri["uncovered_area_m2"] + 0.05):
            worse.append(c)
    out["classes_worse"] = worse
    out["beats_input"] = bool(out["f5_out"] > out["f5_in"] and out["uncovered_out_m2"] <= out["uncovered_in_m2"]
                              and not worse)
    return out


def bench_defect_case(case: Path, work_root: Path, name: str, force: bool, extra: tuple[str, ...] = ()) -> dict:
    """One checkpoint on one defect case: the shipped grades against the labels, input vs merged quality."""
    work = work_root / (f"work-{case.name}-{name}" + "".join(f"-{kv.replace('=', '_')}" for kv in extra))
    if force and work.exists():
        shutil.rmtree(work)
    work_root.mkdir(parents=True, exist_ok=True)
    seconds = run_pipeline(case, work, MODELS[name], work.with_suffix(".log"), extra)
    return {"case": case.name, "checkpoint": name, "sets": list(extra), **labelled_grades(work),
            **input_vs_merged(work), **areas(work), "run_s": seconds}


def print_defect_table(rows: list[dict]) -> None:
    print("defect cases (the real mesh as truth, labelled injected defects): shipped grades against the labels; "
          "F@5cm and uncovered area against the truth; goal: merged beats input, no class worse")
    print(f"{'case':<18} {'checkpoint':<10} {'bad':>5} {'flag':>5} {'R bad':>6} {'P bad':>6} {'F5 in':>6} "
          f"{'F5 out':>6} {'unc in':>7} {'unc out':>7} {'worse':<12} goal")
    for r in rows:
        print(f"{r['case']:<18} {r['checkpoint']:<10} {r['labelled_bad']:>5} {r['flagged']:>5} {r['recall_bad']:>6.3f} "
              f"{r['precision_bad']:>6.3f} {r['f5_in']:>6.3f} {r['f5_out']:>6.3f} {r['uncovered_in_m2']:>7.2f} "
              f"{r['uncovered_out_m2']:>7.2f} {','.join(r['classes_worse']) or '-':<12} "
              f"{'met' if r['beats_input'] else 'missed'}")


def synth_rows(work_dirs: list[str], names: list[str], data: Path) -> dict:
    """``ms3d evaluate`` of each checkpoint on each synth work dir: {campus: {row: {"all", "facade"}}}."""
    from flows.evaluate import campus_rows, evaluate
    from tasks.classify import DEFAULT_MODEL

    models = {n: str(MODELS[n] or DEFAULT_MODEL) for n in names}
    return {Path(w).name: campus_rows(evaluate(models, Path(w).name, w, data=str(data))) for w in work_dirs}


def print_table(case_doc: dict, rows: list[dict]) -> None:
    scan = case_doc["scan"]
    road = scan.get("road_local_m")
    street = (f"street {abs(scan['street_y_m']):g} m off the facade" if road is None or case_doc.get("source_name") == "sceaux"
              else f"along the lane {road}")
    print(f"zero-defect real mesh: {case_doc['mesh']} ({case_doc['faces']:,} faces, {case_doc['area_m2']:.1f} m^2, "
          f"scale {case_doc['scale_factor_m_per_unit']} m/unit, {case_doc['crs']}); MLS {scan['points']:,} points, "
          f"({scan['points'] / case_doc['area_m2']:,.0f} per m^2 of mesh), {scan['passes']} passes, {street}; "
          f"scan to mesh: median {scan['scan_to_mesh_median_m']} m, p99 {scan['scan_to_mesh_p99_m']} m")
    print(f"goal: bad <= {GOAL['bad_share']:.0%}, F@5cm >= {GOAL['f5']}, area within +-{GOAL['area_change']:.0%}"
          + (f"; runs with {' '.join(rows[0]['sets'])}" if rows and rows[0]["sets"] else ""))
    head = (f"{'checkpoint':<10} {'graded':>6} {'bad':>5} {'unk':>4} {'bad %':>6} {'F@5cm':>6} {'P@5':>6} "
            f"{'R@5':>6} {'area in':>8} {'area out':>8} {'change':>7} {'rebuilt':>7} goal")
    print(head)
    for r in rows:
        print(f"{r['checkpoint']:<10} {r['graded']:>6} {r['bad']:>5} {r['unknown']:>4} {100 * r['bad_share']:>5.1f}% "
              f"{r['f5']:>6.3f} {r['p5']:>6.3f} {r['r5']:>6.3f} {r['area_in_m2']:>8.1f} {r['area_out_m2']:>8.1f} "
              f"{100 * r['area_change']:>+6.1f}% {100 * r['rebuilt_area_share']:>6.1f}% "
              f"{'met' if r['meets_goal'] else 'missed'}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sources", default=",".join(SOURCES), help=f"real meshes among {','.join(SOURCES)} "
                    "(each case in ms3d-work/real-cases/<source>-zero)")
    ap.add_argument("--case", type=Path, default=None, help="one zero-defect case folder instead (its source: "
                    "the first of --sources)")
    ap.add_argument("--work-root", type=Path, default=ROOT / "ms3d-work" / "real-mesh-bench")
    ap.add_argument("--mirror", type=Path, default=None, help="bare git folder of the fetched source (one source)")
    ap.add_argument("--mls-density", type=float, default=0.25, help="the case's synth.mls density_scale (give "
                    "another --case and --work-root for another density)")
    ap.add_argument("--street-m", type=float, default=12.0, help="the case's road distance from the facade")
    ap.add_argument("--models", default="default,geo", help=f"checkpoints among {','.join(MODELS)}")
    ap.add_argument("--force", action="store_true", help="empty the work dirs first (a clean run)")
    ap.add_argument("--model", action="append", default=[], metavar="NAME=PATH",
                    help="another checkpoint to bench (a candidate); name it in --models too")
    ap.add_argument("--defect-seeds", default="2", help="defect cases of the zero case, one per seed "
                    "(comma-separated; empty: none)")
    ap.add_argument("--synth", nargs="*", default=[], metavar="WORK_DIR",
                    help="processed labelled synth work dirs scored beside (ms3d evaluate per checkpoint)")
    ap.add_argument("--set", dest="sets", action="append", default=[], metavar="KEY=VALUE",
                    help="extra config override for every run (a diagnosis, e.g. classify.evidence=false); "
                         "its runs get their own work dirs")
    a = ap.parse_args(argv)
    for kv in a.model:
        k, _, v = kv.partition("=")
        MODELS[k] = Path(v).absolute()
    names = a.models.split(",")
    sources = [x for x in a.sources.split(",") if x.strip()]
    rows, defect_rows, cases = [], [], {}
    for src in (sources[:1] if a.case else sources):
        folder = a.case or ROOT / "ms3d-work" / "real-cases" / f"{src}-zero"
        case = build_zero_defect(folder, a.mirror, street_m=a.street_m, density=a.mls_density, source=src)
        case_doc = json.loads((case / "case.json").read_text())
        cases[src] = str(case)
        root = a.work_root if src == "sceaux" else a.work_root / src  # the first source's work dirs as they were
        src_rows = [bench_model(case, root, name, a.force, tuple(a.sets)) | {"source": src} for name in names]
        print_table(case_doc, src_rows)
        rows += src_rows
        src_defects = []
        for seed in [int(x) for x in a.defect_seeds.split(",") if x.strip()]:
            dcase = build_defect_case(case, case.parent / f"{case.name.replace('-zero', '')}-defects-{seed}", seed)
            src_defects += [bench_defect_case(dcase, root, name, a.force, tuple(a.sets)) | {"source": src}
                            for name in names]
        if src_defects:
            print_defect_table(src_defects)
        defect_rows += src_defects
    synth = synth_rows(a.synth, names, a.work_root / "evaluate") if a.synth else {}
    if synth:
        from flows.evaluate_path import spread_table

        print(spread_table(synth))
    out = a.work_root / ("real_mesh_bench-" + "+".join(names) + "".join(f"-{kv.replace('=', '_')}" for kv in a.sets)
                         + ".json")  # one file per checkpoint list: a later run of others does not overwrite it
    out.write_text(json.dumps({"cases": cases, "rows": rows, "defect_rows": defect_rows, "synth": synth},
                              indent=1, default=str))
    print(f"rows: {out}")


if __name__ == "__main__":
    main()
