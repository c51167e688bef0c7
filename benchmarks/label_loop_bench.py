"""Simulated user loop: label the least-sure patches from the truth, fine-tune, re-grade.

    nice -n 10 .venv/bin/python benchmarks/label_loop_bench.py --config CAMPUS.yaml --work WORK_DIR \
        [--n-labels 200] [--out OUT] [--data DATA] [--seeds 7 11] [--synth SYNTH_DIR] [--omp-threads N]

WORK_DIR is a processed, labelled campus (``tiles/*/labels.parquet``: the truth); it is graded in place
(its ``grades.parquet`` and ``labels/`` are rewritten, so pass a copy). CAMPUS.yaml is written by this
script as OUT/campus.yaml from the given config with ``work_dir`` set to WORK_DIR (what ``ms3d train
--campus`` reads). Steps, each timed (wall seconds):

1. grade every tile with the shipped checkpoint (``tasks.classify.run_classify_tile``, as the flow does);
2. propose the ``--n-labels`` least-sure gradable patches (``flows.label_server.least_sure``, the viewer's
   rule: |p(bad) - threshold| smallest) and write their TRUTH labels to ``WORK_DIR/labels/*.csv`` as the
   viewer does (``storage.workdir.user_labels.append_user_label``, one simulated click per second);
3. fine-tune (``flows.finetune.finetune``: the code path of ``ms3d train --campus CONFIG --from default.pt``);
4. re-grade every tile with ``classify.model`` = the fine-tuned checkpoint;
5. with ``--synth`` (the synth campus's folder with truth/): F@5cm before/after through the repair of
   ``quality_bench`` (its sandboxes; the second repair reuses the regions whose patches did not change).

Figures on the gradable pairs WITH a truth label that the simulated user did NOT label: recall, precision,
accuracy and AP on bad, of the model's score alone (before at the shipped threshold; after at the shipped
threshold and at the fine-tuned checkpoint's own) and of the final grade (score + geometric evidence).
``--omp-threads`` unset leaves OpenMP as the CLI does (all cores); the target is <= 10 min on 2 cores.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))


def grade_campus(cfg, work: Path, model: str | None) -> tuple[dict, float]:
    """Grade every live tile with ``model`` (None: the shipped default). Returns ({tile key: (keys (u,) int64,
    score (u,) float32, grade (u,) int8, threshold float)}, wall seconds)."""
    from storage.patches.read import read_side_table
    from storage.workdir.layout import WorkDir
    from tasks.classify import run_classify_tile

    ccfg = cfg.classify.model_copy(update={"enabled": True, "model": model})
    cfg = cfg.model_copy(update={"classify": ccfg, "work_dir": str(work)})
    wd, t0, out = WorkDir(work), time.perf_counter(), {}
    for t in wd.live_tiles():
        res = run_classify_tile(t, cfg, wd)
        if res is None or res.get("status") == "failed":
            raise SystemExit(f"label_loop_bench: classify failed on tile {t.key}: {res}")
        cols, meta = read_side_table(wd.tile_dir(t), "grades")
        out[t.key] = (np.asarray(cols["patch"], np.int64), np.asarray(cols["score"], np.float32),
                      np.asarray(cols["grade"], np.int8), float(meta.get("threshold", 0.5)))
    return out, time.perf_counter() - t0


def truth_of(work: Path, grades: dict) -> dict:
    """{tile key: (u,) int8 truth label aligned with that tile's grade keys; -1 where unlabelled}."""
    from storage.patches.read import read_side_table
    from storage.workdir.layout import WorkDir

    wd, out = WorkDir(work), {}
    for t in wd.live_tiles():
        keys = grades[t.key][0]
        got = read_side_table(wd.tile_dir(t), "labels")
        lab = np.full(len(keys), -1, np.int8)
        if got is not None:
            k, v = np.asarray(got[0]["patch"], np.int64), np.asarray(got[0]["label"], np.int8)
            o = np.argsort(k)
            pos = np.clip(np.searchsorted(k[o], keys), 0, max(len(k) - 1, 0))
            hit = (k[o][pos] == keys) if len(k) else np.zeros(len(keys), bool)
            lab[hit] = v[o][pos[hit]]
        out[t.key] = lab
    return out


def flatten(grades: dict, truth: dict) -> dict:
    """The campus's patches as flat arrays: keys, score, grade, threshold, truth."""
    tiles = sorted(grades)
    return {"keys": np.concatenate([grades[t][0] for t in tiles]),
            "score": np.concatenate([grades[t][1] for t in tiles]).astype(np.float64),
            "grade": np.concatenate([grades[t][2] for t in tiles]),
            "threshold": np.concatenate([np.full(len(grades[t][0]), grades[t][3]) for t in tiles]),
            "truth": np.concatenate([truth[t] for t in tiles])}


def simulate_user(work: Path, flat: dict, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Label the n least-sure labelled gradable patches with their truth, as clicks in the viewer would
    (``labels/`` is emptied first). Returns ((n,) int64 keys, (n,) int8 labels)."""
    from flows.label_server import least_sure
    from storage.grid import PatchGrid
    from storage.workdir.user_labels import LABELS_DIR, append_user_label

    scores = np.where(flat["truth"] >= 0, flat["score"], np.nan)  # a user labels what they can judge
    pick = least_sure(flat["keys"], scores, flat["threshold"], n)
    shutil.rmtree(work / LABELS_DIR, ignore_errors=True)
    t0 = dt.datetime.now(dt.UTC).replace(microsecond=0)
    for s, (ijk, lab) in enumerate(zip(PatchGrid.unpack(flat["keys"][pick]), flat["truth"][pick])):
        append_user_label(work, tuple(int(v) for v in ijk), int(lab), t0 + dt.timedelta(seconds=s))
    return flat["keys"][pick], flat["truth"][pick]


def figures(truth: np.ndarray, score: np.ndarray, pred: np.ndarray) -> dict:
    """Bad-class figures of (n,) truth {0,1}, (n,) score p(bad) and (n,) bool predicted bad."""
    from ms3d_model.metrics import average_precision

    y = truth == 1
    tp = int((y & pred).sum())
    return {"n": len(y), "n_bad": int(y.sum()), "recall": tp / max(int(y.sum()), 1),
            "precision": tp / max(int(pred.sum()), 1), "acc": float((y == pred).mean()),
            "ap": float(average_precision(y, score))}


def grading_rows(before: dict, after: dict, user_keys: np.ndarray, ft_threshold: float) -> list[tuple[str, dict]]:
    """The table's rows over the gradable, truth-labelled patches the user did not label."""
    assert np.array_equal(before["keys"], after["keys"])
    m = np.isfinite(before["score"]) & np.isfinite(after["score"]) & (before["truth"] >= 0)
    m &= ~np.isin(before["keys"], user_keys)
    y, sb, sa = before["truth"][m], before["score"][m], after["score"][m]
    shipped = float(np.median(before["threshold"]))
    return [(f"shipped, score >= {shipped:.3f}", figures(y, sb, sb >= shipped)),
            (f"fine-tuned, score >= {shipped:.3f} (shipped thr.)", figures(y, sa, sa >= shipped)),
            (f"fine-tuned, score >= {ft_threshold:.3f} (own thr.)", figures(y, sa, sa >= ft_threshold)),
            ("shipped, final grade (+evidence)", figures(y, sb, before["grade"][m] == 1)),
            ("fine-tuned, final grade (+evidence)", figures(y, sa, after["grade"][m] == 1))]


def quality_before_after(work: Path, synth: Path, out: Path, before: dict, after: dict, log=print) -> dict:
    """F@5cm etc. of the repaired campus with the before and after grades (``quality_bench``'s sandbox,
    repair and assembly); the after pass re-runs only the regions whose patches changed."""
    import quality_bench as qb
    from _quality_eval import evaluate, mls_seen, subdivided_truth

    from storage.patches.read import PatchStore
    from storage.patches.write import write_side_table
    from storage.workdir.layout import WorkDir, campus_frame, read_campus

    origin = np.asarray(campus_frame(read_campus(WorkDir(work))).origin, np.float64)
    truth = subdivided_truth(synth, origin)
    seen = mls_seen(*truth, work)
    res, sb = {}, out / "quality-sandbox"
    for name, g in (("before", before), ("after", after)):
        t0 = time.perf_counter()
        if name == "before":
            qb.make_sandbox(work, sb, {t: v[2] for t, v in g.items()})
        else:
            for t, v in g.items():
                store = PatchStore(sb / "tiles" / t)
                (sb / "tiles" / t / "grades.parquet").unlink()
                write_side_table(sb / "tiles" / t, "grades", {"patch": store.patches()["patch"],
                                 "score": v[2].astype(np.float32), "grade": v[2]}, store.meta, model_hash="label_loop")
        rows = qb.run_repair(sb, log=log)
        v, f, info = qb.assemble(sb)
        r = evaluate(v, f, truth, seen)
        res[name] = {"F5_seen": r["seen"]["F5"], "F5_all": r["all"]["F5"], "F5_campus": r["campus"]["F5"],
                     "uncovered_seen": r["seen"].get("uncovered"), "n_regions": len(rows),
                     "n_regions_run": sum(1 for x in rows if not x.get("skipped")),
                     "n_failed": sum(1 for x in rows if x.get("status") == "failed"),
                     "seconds": time.perf_counter() - t0, **info}
        log(f"  quality {name}: {json.dumps(res[name], default=float)}")
    return res


def print_table(rows: list[tuple[str, dict]], quality: dict | None) -> str:
    lines = ["| grader | pairs (bad) | recall | precision | accuracy | AP(bad) |", "|---|---|---|---|---|---|"]
    lines += [f"| {n} | {f['n']} ({f['n_bad']}) | {f['recall']:.3f} | {f['precision']:.3f} | "
              f"{100 * f['acc']:.1f} % | {f['ap']:.3f} |" for n, f in rows]
    if quality:
        lines += ["", "| repair with | F@5cm seen facades | F@5cm all facades | F@5cm campus | regions (run) |",
                  "|---|---|---|---|---|"]
        lines += [f"| {k} grades | {q['F5_seen']:.3f} | {q['F5_all']:.3f} | {q['F5_campus']:.3f} | "
                  f"{q['n_regions']} ({q['n_regions_run']}) |" for k, q in quality.items()]
    text = "\n".join(lines)
    print(text, flush=True)
    return text


def campus_config(config: Path, work: Path, out: Path) -> tuple[object, Path]:
    """The campus config with work_dir = ``work``, written to OUT/campus.yaml (what fine-tuning reads)."""
    import yaml

    from tasks.config import CampusConfig

    cfg = CampusConfig.from_yaml(config, {"work_dir": str(work.resolve())})
    path = out / "campus.yaml"
    path.write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    return cfg, path


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", type=Path, required=True, help="the campus YAML (its work_dir is replaced by --work)")
    ap.add_argument("--work", type=Path, required=True, help="a processed labelled work dir (graded in place: a copy)")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--n-labels", type=int, default=200)
    ap.add_argument("--base", default=None, help="checkpoint to start from (default: the shipped default.pt)")
    ap.add_argument("--data", default="ms3d-work", help="synth campuses and caches of `ms3d train` (as its --data)")
    ap.add_argument("--seeds", nargs="*", default=["7", "11"], help="synth campuses mixed in (as `ms3d train --seeds`: SEED, SEED@DENSITY, SEED:coarse)")
    ap.add_argument("--mix-work-dir", action="append", default=[], help="a labelled work dir mixed in as well")
    ap.add_argument("--synth", type=Path, default=None, help="the campus's synth folder (truth/): F@5cm before/after")
    ap.add_argument("--omp-threads", type=int, default=None, help="OMP_NUM_THREADS of the fine-tune (unset: as the CLI)")
    a = ap.parse_args(argv)
    if a.omp_threads:  # before sklearn / torch start their pools
        os.environ["OMP_NUM_THREADS"] = str(a.omp_threads)
    from flows.finetune import FinetuneSpec, finetune
    from tasks.classify import DEFAULT_MODEL

    out = (a.out or a.work.parent / f"{a.work.name}-label-loop").resolve()
    out.mkdir(parents=True, exist_ok=True)
    cfg, cfg_path = campus_config(a.config, a.work, out)
    walls = {}
    from ms3d_model.train import model_hash

    base = str(Path(a.base).resolve()) if a.base else str(DEFAULT_MODEL)
    print(f"base checkpoint {base} (sha256 {model_hash(base)[:16]}); synth mix: seeds {a.seeds} + {a.mix_work_dir}",
          flush=True)
    g0, walls["grade_before_s"] = grade_campus(cfg, a.work, base)
    truth = truth_of(a.work, g0)
    before = flatten(g0, truth)
    user_keys, user_labels = simulate_user(a.work, before, a.n_labels)
    print(f"graded {len(before['keys'])} patches ({int(np.isfinite(before['score']).sum())} pairs) in "
          f"{walls['grade_before_s']:.0f} s; simulated user labelled {len(user_keys)} least-sure patches "
          f"({int(user_labels.sum())} bad) into {a.work / 'labels'}", flush=True)
    spec = FinetuneSpec(campus=str(cfg_path), base=base, out=str(out / "finetune"),
                        seeds=a.seeds, work_dirs=a.mix_work_dir, data=a.data)
    t0 = time.perf_counter()
    ft = finetune(spec)
    walls["finetune_s"] = time.perf_counter() - t0
    print(f"fine-tune: {walls['finetune_s']:.1f} s wall (trees {ft['fit_seconds']:.1f} s), OMP_NUM_THREADS="
          f"{os.environ.get('OMP_NUM_THREADS', 'unset')}, os.cpu_count()={os.cpu_count()} -> {ft['checkpoint']}", flush=True)
    g1, walls["grade_after_s"] = grade_campus(cfg, a.work, ft["checkpoint"])
    after = flatten(g1, truth)
    rows = grading_rows(before, after, user_keys, float(ft["validation"]["threshold"]))
    print(f"\nSimulated user loop: {len(user_keys)} least-sure patches labelled from the truth; figures on the "
          f"{rows[0][1]['n']} truth-labelled pairs they do not include")
    text = print_table(rows, None)
    quality = None
    if a.synth is not None:
        t0 = time.perf_counter()
        quality = quality_before_after(a.work, a.synth, out, g0, g1)
        walls["quality_s"] = time.perf_counter() - t0
        text = print_table(rows, quality)
    print("wall seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in walls.items()))
    summary = {"base": base, "base_sha256": model_hash(base), "rows": dict(rows), "quality": quality,
               "walls": walls, "n_labels": len(user_keys),
               "n_labels_bad": int(user_labels.sum()), "finetune": {k: ft[k] for k in (
                   "checkpoint", "n_user_train", "n_user_heldout", "n_synth_train", "fit_seconds", "wall_seconds",
                   "heldout_user", "validation")}, "table": text}
    (out / "label_loop.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary


if __name__ == "__main__":
    main()
