"""Candidate graders scored per family, the model alone: the numbers the default checkpoint is chosen by.

    .venv/bin/python benchmarks/grader_families.py --model NAME=PATH [--model ...] \\
        --family synth-val=TRAIN_SUMMARY_JSON ... --family "sceaux zero=WORK_DIR" --family "sceaux defects=WORK_DIR" ...

A family is the validation pairs of a featurised training set (``NAME=.../pairs_<key>.npz``, split as ``ms3d
train`` splits it: every checkpoint scored on the same pairs), the figures a training run recorded
(``NAME=.../summary_*.json``; a checkpoint not trained in that run shows "-"), or processed, labelled
work dirs (one or more, comma-separated: a real mesh's zero-defect case, its defect cases, unseen synth
campuses). Per family and checkpoint it prints AP(bad), precision and recall on bad at the checkpoint's own
threshold and the flagged share, pooled over the family's work dirs (each checkpoint scores every pair;
``flows.evaluate``'s model-alone row). The worst family is the one whose figure against its goal is worst: a
zero-defect family (no labelled bad pair) by its flagged share (goal <= 3 %), another by recall on bad at
precision on bad (goal R >= 0.85 at P >= 0.80). Writes the rows as JSON (``--out``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ZERO_GOAL, RECALL_GOAL, PRECISION_GOAL = 0.03, 0.85, 0.80


def family_scores(models: dict[str, str], work_dirs: list[str], cache: str) -> dict[str, dict]:
    """{model: report} of each checkpoint on the pooled labelled pairs of ``work_dirs`` (model alone)."""
    from flows.evaluate_path import with_flagged
    from ms3d_model.dataset import PairSet
    from ms3d_model.metrics import classification_report
    from ms3d_model.train import checkpoint_threshold, load_checkpoint, predict
    from tasks.classify import campus_pair_set

    keys = ("n", "ap_bad", "precision_bad", "recall_bad", "flagged_share")
    out, sets = {}, {}
    for name, path in models.items():
        net, prof, meta = load_checkpoint(path)
        size = (prof.max_points, prof.max_faces, prof.k_centre, prof.seed)
        if size not in sets:
            sets[size] = [campus_pair_set(w, Path(w).name, *size, cache_dir=cache) for w in work_dirs]
        parts = sets[size]
        ps = PairSet.concat(parts)
        thr = checkpoint_threshold(meta)
        p = predict(net, ps, 1024)
        rep = with_flagged(classification_report(ps.labels, p, thr))
        out[name] = {k: rep[k] for k in keys} | {"labelled_bad": int((ps.labels == 1).sum()), "threshold": thr}
        if len(parts) > 1:  # each campus apart too: the spread
            bounds = np.cumsum([0] + [len(q) for q in parts])
            out[name]["campuses"] = {
                Path(w).name: {k: r[k] for k in keys} for w, a, b in zip(work_dirs, bounds[:-1], bounds[1:])
                if (r := with_flagged(classification_report(ps.labels[a:b], p[a:b], thr)))}
    return out


def validation_scores(models: dict[str, str], pairs_npz: str, block_m: float = 20.0, val_fraction: float = 0.2,
                      seed: int = 0, buffer_m: float = 3.0) -> dict[str, dict]:
    """{model: report} on the validation pairs of a featurised training set (``ms3d train``'s cached
    ``pairs_<key>.npz``), split as ``ms3d train`` splits it (20 m blocks, 20 %, seed 0, ``--buffer-m``): the same
    pairs for every checkpoint, whichever campuses it was trained on."""
    from flows.evaluate_path import with_flagged
    from ms3d_model.dataset import area_split, load_pair_set
    from ms3d_model.metrics import classification_report
    from ms3d_model.train import checkpoint_threshold, load_checkpoint, predict
    from storage.grid import PatchGrid

    ps = load_pair_set(pairs_npz)
    _, val = area_split(ps.ijk, PatchGrid().size_m, ps.campus, block_m, val_fraction, seed, buffer_m)
    ps = ps.take(np.flatnonzero(val))
    out = {}
    for name, path in models.items():
        net, _, meta = load_checkpoint(path)
        thr = checkpoint_threshold(meta)
        rep = with_flagged(classification_report(ps.labels, predict(net, ps, 1024), thr))
        out[name] = {k: rep[k] for k in ("n", "ap_bad", "precision_bad", "recall_bad", "flagged_share")} | {
            "labelled_bad": int((ps.labels == 1).sum()), "threshold": thr}
    return out


def summary_scores(models: dict[str, str], summary: str) -> dict[str, dict]:
    """{model: report} from a training summary: the validation figures it recorded for a checkpoint of its own."""
    doc = json.loads(Path(summary).read_text())
    by_path = {str(Path(m["best_path"]).resolve()): m["best"] for m in doc["models"].values()}
    out = {}
    for name, path in models.items():
        b = by_path.get(str(Path(path).resolve()))
        if b is not None:
            cm = np.asarray(b.get("confusion", [[0, 0], [0, 0]]))
            out[name] = {"n": b.get("n"), "ap_bad": b.get("ap_bad"), "precision_bad": b.get("precision_bad"),
                         "recall_bad": b.get("recall_bad"), "flagged_share": float(cm[:, 1].sum() / max(cm.sum(), 1)),
                         "labelled_bad": int(cm[1].sum()), "threshold": b.get("threshold")}
    return out


def goal_margin(rep: dict) -> float:
    """How far a family's figure is past its goal (negative: missed): flagged share on a zero-defect family,
    else recall on bad (with its precision below the floor counting as a miss)."""
    if rep.get("labelled_bad", 0) == 0:
        return ZERO_GOAL - rep["flagged_share"]
    p = rep["precision_bad"] if np.isfinite(rep["precision_bad"]) else 0.0
    return min(rep["recall_bad"] - RECALL_GOAL, p - PRECISION_GOAL)


def print_table(rows: dict[str, dict[str, dict]], models: list[str]) -> None:
    print(f"{'family':<24} {'model':<14} {'pairs':>6} {'bad':>5} {'AP bad':>7} {'P bad':>6} {'R bad':>6} {'flagged':>8} "
          f"{'margin':>7}")
    for fam, per_model in rows.items():
        for m in models:
            r = per_model.get(m)
            if r is None:
                print(f"{fam:<24} {m:<14} {'-':>6}")
                continue
            fmt = lambda v: f"{v:.3f}" if v is not None and np.isfinite(v) else "-"  # noqa: E731
            print(f"{fam:<24} {m:<14} {r['n'] or 0:>6} {r['labelled_bad']:>5} {fmt(r['ap_bad']):>7} "
                  f"{fmt(r['precision_bad']):>6} {fmt(r['recall_bad']):>6} {100 * r['flagged_share']:>7.1f}% "
                  f"{goal_margin(r):>+7.3f}")
    spread = [(fam, m, r["campuses"]) for fam, per_model in rows.items() for m in models
              if (r := per_model.get(m)) and r.get("campuses")]
    if spread:
        print("per campus, mean [min, max]:")
        for fam, m, camps in spread:
            cells = []
            for k in ("ap_bad", "precision_bad", "recall_bad"):
                x = np.array([c[k] for c in camps.values()], np.float64)
                x = x[np.isfinite(x)]
                cells.append(f"{k} {x.mean():.3f} [{x.min():.3f}, {x.max():.3f}]" if len(x) else f"{k} -")
            print(f"  {fam:<22} {m:<14} " + "  ".join(cells))
    print("worst family per model (the smallest margin against its goal):")
    for m in models:
        fams = {f: goal_margin(p[m]) for f, p in rows.items() if m in p}
        worst = min(fams, key=fams.get)
        print(f"  {m:<14} {worst} ({fams[worst]:+.3f})")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", action="append", required=True, metavar="NAME=PATH")
    ap.add_argument("--family", action="append", required=True, metavar="NAME=SUMMARY.json|WORK_DIR[,WORK_DIR...]")
    ap.add_argument("--cache", default="ms3d-work/families-cache", help="featurised pairs (keyed by the stores)")
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args(argv)
    models = dict(kv.split("=", 1) for kv in a.model)
    rows = {}
    for fam in a.family:
        name, _, where = fam.partition("=")
        rows[name] = (summary_scores(models, where) if where.endswith(".json")
                      else validation_scores(models, where) if where.endswith(".npz")
                      else family_scores(models, where.split(","), a.cache))
    print_table(rows, list(models))
    if a.out:
        a.out.write_text(json.dumps(rows, indent=1, default=float))


if __name__ == "__main__":
    main()
