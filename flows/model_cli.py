"""The ``ms3d train`` and ``ms3d evaluate`` commands (added to the ``ms3d`` parser by ``add_commands``)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path


def _cmd_finetune(a) -> int:
    from flows.finetune import FinetuneSpec, finetune

    spec = FinetuneSpec(campus=a.campus, base=a.base, out=a.out, seeds=a.seeds, work_dirs=a.work_dir or [],
                        data=a.data, holdout=a.holdout, user_weight=a.user_weight, block_m=a.block_m)
    logging.getLogger("ms3d").setLevel(logging.INFO)
    s = finetune(spec)
    for name, f in s["heldout_user"].items():
        print(f"{name:<10} held-out user labels: {f['n']} pairs ({f['n_bad']} bad)  acc {100 * f['acc']:.1f} %  "
              f"precision {f['precision_bad']:.3f} recall {f['recall_bad']:.3f} at threshold {f['threshold']:.3f}")
    print(f"{s['n_user_train']} user pairs (x{s['user_weight']}) + {s['n_synth_train']} synth pairs; "
          f"{s['wall_seconds']:.1f} s -> {s['checkpoint']} (MODEL_CARD.md beside it); "
          f"set classify.model to it and re-run to re-grade")
    return 0


def _cmd_train(a) -> int:
    from flows.train import TrainSpec, suite, train

    if a.campus or a.base:
        if not (a.campus and a.base):
            raise SystemExit("ms3d train: --campus and --from go together (fine-tune a checkpoint on a campus's labels)")
        return _cmd_finetune(a)

    overrides = {}
    for kv in a.set or []:
        k, _, v = kv.partition("=")
        try:
            overrides[k] = json.loads(v)
        except json.JSONDecodeError:
            overrides[k] = v
    if a.paper_training:
        from ms3d_model.profiles import PAPER_TRAINING

        overrides = PAPER_TRAINING | overrides  # --set still wins
    if "milestones" in overrides:
        overrides["milestones"] = tuple(overrides["milestones"])
    if "gbm_ignored_cues" in overrides:
        overrides["gbm_ignored_cues"] = tuple(overrides["gbm_ignored_cues"])
    models = list(suite()) if a.suite else (a.models or ["ms3dqe"])
    spec = TrainSpec(out=a.out, data=a.data, seeds=a.seeds, work_dirs=a.work_dir or [], profile=a.profile,
                     overrides=overrides, models=models, block_m=a.block_m, buffer_m=a.buffer_m,
                     progress=sys.stderr.isatty(), workers=a.workers)
    logging.getLogger("ms3d").setLevel(logging.INFO)
    summary = train(spec, use_prefect=not a.no_prefect)
    for name, m in summary["models"].items():
        b = m["best"]
        print(f"{name:<12} val AP(bad) {100 * b['ap_bad']:.1f} %  mAP {100 * b['map']:.1f} %  at threshold "
              f"{b['threshold']:.3f}: precision {b['precision_bad']:.3f} recall {b['recall_bad']:.3f} "
              f"acc {100 * b['acc']:.1f} %  epoch {b['epoch']}  {m['parameters']:,} parameters  "
              f"{m['train_seconds']:.0f} s wall / {m['train_cpu_seconds']:.0f} s CPU  -> {m['best_path']}")
    print(f"{summary['n_pairs']} pairs ({summary['n_train']} train, {summary['n_val']} validation, "
          f"{summary['buffer_m']:.1f} m buffer); summary in {a.out}/summary_*.json")
    return 0


def _cmd_evaluate(a) -> int:
    from flows.evaluate import campus_rows, evaluate, held_out_campus, suite_models
    from flows.evaluate_path import spread_table

    models = suite_models(a.suite) if a.suite else {}
    for kv in a.model or []:
        name, _, path = kv.partition("=")
        models[name if path else "ms3dqe"] = path or name
    if not models:
        from tasks.classify import DEFAULT_MODEL

        models = {"ms3dqe": str(DEFAULT_MODEL)}
    logging.getLogger("ms3d").setLevel(logging.INFO)
    campuses = [held_out_campus(None, w, None, a.data) for w in a.work_dir or []]
    campuses += [held_out_campus(None, None, c, a.data) for c in a.campus or []]
    if not campuses or a.seed:
        campuses += [held_out_campus(s, None, None, a.data) for s in (a.seed or [42])]
    per_campus = {}
    for name, wd in campuses:
        out = a.out if len(campuses) == 1 or not a.out else str(Path(a.out).with_suffix("")) + f"_{name}.json"
        res = evaluate(models, name, wd, data=a.data, out=out, threads=a.threads, max_pairs=a.max_pairs)
        print(res["text"])
        per_campus[name] = campus_rows(res)
    if len(per_campus) > 1:
        print("\n" + spread_table(per_campus))
        if a.out:
            Path(a.out).write_text(json.dumps(per_campus, indent=1, default=str))
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    """Add ``train`` and ``evaluate`` to the ``ms3d`` subcommands."""
    t = sub.add_parser("train", help="train MS3DQE-Net (and the baselines) on synth campuses")
    t.add_argument("--profile", default="default", help="default | paper | tiny (ms3d_model.profiles)")
    t.add_argument("--seeds", nargs="*", default=[7, 11], help="synth demo campuses to train on: SEED, SEED@DENSITY "
                   "(MLS density, 1.0 = a real scanner's) or SEED:coarse (a LoD2-like block model as the mesh)")
    t.add_argument("--work-dir", action="append", help="a processed, labelled campus to train on as well")
    t.add_argument("--data", default="ms3d-work", help="where synth campuses, their work dirs and caches live")
    t.add_argument("--out", default="ms3d-work/train")
    t.add_argument("--workers", type=int, default=2, help="training campuses prepared side by side (processes)")
    t.add_argument("--models", nargs="*", help="networks to train (ms3dqe, ms3dqe_plus, ms3dqe_geo, pointnet, "
                   "pointnet2, pointcnn, meshnet, gbm, ablation1..6)")
    t.add_argument("--suite", action="store_true", help="train every network of Tables 3 and 4")
    t.add_argument("--set", action="append", metavar="KEY=VALUE", help="override a profile field, e.g. epochs=3")
    t.add_argument("--paper-training", action="store_true",
                   help="the paper's optimiser, loss and selection (SGD, MultiStepLR, batch 8, plain cross-entropy, "
                        "best accuracy) instead of AdamW + one-cycle, balanced loss, best AP on bad")
    t.add_argument("--block-m", type=float, default=20.0, help="side of the square ground blocks validation is "
                                                               "drawn in (metres; 10 suits the tiny synth campuses)")
    t.add_argument("--buffer-m", type=float, help="gap between training and validation pairs (metres; default: the "
                                                  "largest defect's extent, at most half a block)")
    t.add_argument("--no-prefect", action="store_true", help="run without a Prefect server")
    t.add_argument("--campus", metavar="CONFIG", help="fine-tune on this campus's user labels (WORKDIR/labels/*.csv, "
                                                      "from `ms3d view --label`) mixed with the synth pairs")
    t.add_argument("--from", dest="base", metavar="CHECKPOINT", help="the checkpoint to fine-tune (with --campus), "
                                                                     "e.g. ms3d_model/weights/default.pt")
    t.add_argument("--holdout", type=float, default=0.25, help="share of the user's labels held out for validation")
    t.add_argument("--user-weight", type=int, default=10, help="how many synth pairs one user-labelled pair counts as")
    t.set_defaults(func=_cmd_train)

    e = sub.add_parser("evaluate", help="Tables 3 and 4 on a held-out campus")
    e.add_argument("--suite", help="a `ms3d train --suite` output folder")
    e.add_argument("--model", action="append", metavar="NAME=PATH", help="a checkpoint to score (repeatable)")
    e.add_argument("--seed", type=int, action="append", help="held-out synth demo campus, never trained on "
                   "(repeatable; default 42 when no --work-dir or --campus is given)")
    e.add_argument("--work-dir", action="append", help="score a processed labelled campus instead (repeatable: "
                   "each campus is scored, then the mean and spread over them)")
    e.add_argument("--campus", action="append", help="score a campus config (YAML with inputs.labels; repeatable)")
    e.add_argument("--threads", type=int, default=1, help="torch threads (1 is fastest on a busy 2-core machine)")
    e.add_argument("--max-pairs", type=int, help="score a seeded random subset of this many labelled pairs")
    e.add_argument("--data", default="ms3d-work")
    e.add_argument("--out", help="write the results as JSON here")
    e.set_defaults(func=_cmd_evaluate)
