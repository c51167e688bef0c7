"""``ms3d evaluate``: score trained models on a held-out campus and print the paper's Tables 3 and 4.

    ms3d evaluate --suite ms3d-work/train --seed 42 --train-seeds 7 11

The held-out campus is a synth ``demo`` campus of a seed never used in training (generated and processed
under ``--data`` when missing), or any labelled campus: ``--work-dir`` (processed) or ``--campus`` (a
YAML config with ``inputs.labels``; processed first). Every model is scored on the same pairs: Acc, mAP,
per-class precision / recall / F1, confusion matrix (Acc, P/R/F1 and the confusion at the checkpoint's own
operating threshold, ``ms3d_model.train.checkpoint_threshold``, printed beside them; mAP needs none); its forward time per pair at batch 1 and at the best
batch size (network only, featurised inputs, as the paper times it) and its parameter count. The
gradient-boosting baseline comes from the same training run (``ms3d train --suite``: its trees are
stored as a TreeNet checkpoint) and is timed on its trees alone (cue extraction reported beside).

Results are keyed by what each checkpoint *is* (``ms3d_model.report.model_kind``, from its architecture),
not by the name it was passed under: ``ms3d evaluate --work-dir W`` scores the shipped default, the GBM
trees, and reports them in the GBM row, never in MS3DQE-Net's. Every row names its checkpoint.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from flows.evaluate_path import FACADE_MAX_HORIZONTAL, FIGURES, facade_mask, shipped_scores, with_flagged

log = logging.getLogger("ms3d.evaluate")

SUITE_CASES = {"ablation1": "(1)", "ablation2": "(2)", "ablation3": "(3)", "ablation4": "(4)", "ablation5": "(5)",
               "ablation6": "(6)", "ablationFull": "Full"}


def forward_seconds(net, ps, batch_sizes=(1, 8, 32, 64, 128), uses_cues=False, repeats: int = 3) -> dict:
    """Seconds per pair of the network's forward pass (eval mode, featurised inputs) at each batch size:
    {"sec_b1", "sec_best", "best_batch", "by_batch": {b: s}}; the minimum over ``repeats`` runs of ~128 pairs."""
    import torch

    from ms3d_model.dataset import to_batch

    net.eval()
    by = {}
    with torch.inference_mode():
        for b in batch_sizes:
            if b > len(ps):
                continue
            n_batches = max(1, min(128 // b, len(ps) // b))
            batches = [to_batch(ps.feats.take(np.arange(i * b, (i + 1) * b)),
                                ps.cues[i * b:(i + 1) * b] if uses_cues else None) for i in range(n_batches)]
            net(batches[0])
            best = float("inf")
            for _ in range(repeats):
                t = time.perf_counter()
                for x in batches:
                    net(x)
                best = min(best, (time.perf_counter() - t) / (n_batches * b))
            by[b] = best
    best_b = min(by, key=by.get)
    return {"sec_b1": by.get(1), "sec_best": by[best_b], "best_batch": best_b, "by_batch": by}


def held_out_campus(seed: int | None, work_dir: str | None, campus: str | None, data: str) -> tuple[str, str]:
    """(name, processed work dir) of the evaluation campus."""
    from flows.train import prepare_campus

    if work_dir:
        return Path(work_dir).name, work_dir
    if campus:
        from flows.campus import run_campus
        from tasks.config import CampusConfig

        cfg = CampusConfig.from_yaml(campus, {"runner": "inline", "classify": {"enabled": False}})
        if not cfg.inputs.labels:
            raise ValueError(f"{campus}: evaluation needs inputs.labels (a defects.json or a label CSV)")
        if not any(Path(cfg.work_dir).glob("tiles/*/labels.parquet")):
            run_campus(cfg, progress=False)
        return cfg.name, cfg.work_dir
    return f"s{seed}", prepare_campus(seed, data)


def evaluate(models: dict[str, str], eval_name: str, eval_wd: str, data: str = "ms3d-work", out: str | None = None,
             threads: int = 1, max_pairs: int | None = None, previous: dict | None = None) -> dict:
    """Score checkpoints ({suite name: path}, the GBM baseline's TreeNet included) on a campus; returns the
    results and the printed tables under "text". ``max_pairs``: score a seeded random subset of the campus's
    labelled pairs (the same subset for every model); ``previous``: results of models scored before (merged
    into the tables)."""
    import torch

    from ms3d_model.net import kernel_response_stats, n_parameters
    from ms3d_model.report import model_kind, model_label, per_class, table3, table4
    from ms3d_model.train import checkpoint_threshold, load_checkpoint, net_uses_cues, predict
    from tasks.classify import campus_pair_set

    torch.set_num_threads(threads)
    cache = str(Path(data) / "cache")
    results, configs, held = {}, {}, {}
    kc = {}
    for name, path in models.items():
        net, prof, meta = load_checkpoint(path)
        thr = checkpoint_threshold(meta)
        size = (prof.max_points, prof.max_faces, prof.k_centre, prof.seed)
        if size not in held:
            ps = campus_pair_set(eval_wd, eval_name, *size, cache_dir=cache)
            if max_pairs and len(ps) > max_pairs:
                ps = ps.take(np.sort(np.random.default_rng(0).permutation(len(ps))[:max_pairs]))
            held[size] = ps
        ps = held[size]
        t = time.perf_counter()
        p = predict(net, ps, prof.eval_batch)
        rep = scoped_report(ps, p, thr)
        rep.update(forward_seconds(net, ps, uses_cues=net_uses_cues(net)))
        n_par = int(net.feature.numel()) if prof.net.arch == "gbm" else n_parameters(net)  # trees: node count
        rep.update({"parameters": n_par, "profile": prof.name, "path": str(path),
                    "max_points": prof.max_points, "max_faces": prof.max_faces, "predict_seconds": time.perf_counter() - t})
        rep["net"] = prof.net.to_json()
        rep["model"] = model_label(rep["net"], path)
        key = _result_key(name, model_kind(rep["net"]), results)
        if key != name:
            log.info("%s was passed as %r but is a %s checkpoint: scored as %r", path, name,
                     model_kind(rep["net"]), key)
        rep["passed_as"] = name
        results[key] = rep
        configs[key] = rep["net"]
        if key == "ms3dqe" and model_kind(rep["net"]) == "ms3dqe":
            from ms3d_model.dataset import to_batch

            kc = kernel_response_stats(net, to_batch(ps.feats.take(np.arange(min(64, len(ps))))))
        log.info("%s: threshold %.4f acc %.4f mAP %.4f", rep["model"], thr, rep["acc"], rep["map"])
    shipped = shipped_path_row(eval_wd, held)
    trees = [k for k, r in results.items() if model_kind(r["net"]) == "gbm"]
    cue_s = _cue_seconds_per_pair(eval_wd) if trees else float("nan")
    for k in trees:
        results[k]["cue_seconds_per_pair"] = cue_s
    for name, rep in (previous or {}).items():
        results.setdefault(name, rep)
        configs.setdefault(name, rep.get("net", {}))
    n = max((r["n"] for r in results.values()), default=0)
    full = "ablationFull" if "ablationFull" in results else "ms3dqe"  # the Full row at the ablations' budget
    names = {**SUITE_CASES, full: "Full"}
    cases = {names[k]: v for k, v in results.items() if k in names}
    case_cfg = {names[k]: v for k, v in configs.items() if k in names}
    text = "\n\n".join([table3(results), table4(cases, case_cfg), per_class(results)])
    text += "\n\n" + path_table(results, shipped)
    if trees:
        text += (f"\n\nGBM time is the trees alone; its input, the hand-made cues, costs "
                 f"{cue_s * 1000:.1f} ms per pair to extract (the networks' featurisation is not timed either).")
    if kc:
        text += "\n\nKernel-correlation responses of the trained MS3DQE-Net on held-out pairs:\n" + "\n".join(
            f"  {k:<14} mean {v['mean']:.3g}  median {v['median']:.3g}  >1e-3 {100 * v['frac_gt_1e-3']:.1f} %  "
            f">0.1 {100 * v['frac_gt_0.1']:.1f} %" for k, v in kc.items())
    text = f"Held-out campus {eval_name} ({eval_wd}): {n} labelled pairs\n\n" + text
    res = {"campus": eval_name, "work_dir": eval_wd, "results": results, "shipped_path": shipped,
           "kernel_stats": kc, "text": text}
    if out:
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        Path(out).write_text(json.dumps(res, indent=1, default=str))
    return res


def scoped_report(ps, p_bad: np.ndarray, thr: float) -> dict:
    """The classification report of scores ``p_bad`` (B,) on the pairs ``ps`` at ``thr``, with its "all" and
    "facade" scopes (and the flagged share) beside it."""
    from ms3d_model.metrics import classification_report

    rep = with_flagged(classification_report(ps.labels, p_bad, thr))
    rep["threshold"] = thr
    rep["all"] = {k: rep[k] for k in (*FIGURES, "n")}
    fac = facade_mask(ps.cues)
    rep["facade"] = with_flagged(classification_report(ps.labels[fac], p_bad[fac], thr)) if fac.any() else {}
    return rep


def _row_name(key: str, rep: dict) -> str:
    """A row's name: the checkpoint's label, after the name it was passed under unless that is a kind's."""
    name, label = rep.get("passed_as", key), rep.get("model", key)
    return label if name in ("gbm", "ms3dqe") else f"{name}: {label}"


def campus_rows(res: dict) -> dict:
    """{row name: {"all": figures, "facade": figures}} of one campus's results (models and shipped path)."""
    rows = {_row_name(k, r): {"all": r.get("all", {}), "facade": r.get("facade", {})}
            for k, r in res["results"].items()}
    if res.get("shipped_path"):
        sp = res["shipped_path"]
        rows[f"shipped path: {sp['grader']}"] = {"all": sp["all"], "facade": sp["facade"]}
    return rows


def shipped_path_row(eval_wd: str, held: dict) -> dict | None:
    """The shipped grading path's figures on the campus (its stored grades against the labels, all pairs and
    facades), or None when the campus was processed without classify."""
    if not held:
        return None
    ps = next(iter(held.values()))
    got = shipped_scores(eval_wd, ps.ijk)
    if got is None:
        return None
    flagged, score, meta = got
    rep = scoped_report(ps, score, float(meta.get("threshold", 0.5)))
    row = {"grader": meta.get("grader", "?"), "model": meta.get("model", "?"), "threshold": rep["threshold"],
           "all": {k: v for k, v in rep.items() if k not in ("all", "facade")}, "facade": rep["facade"]}
    row["all"]["flagged"] = int(flagged.sum())
    return row


def path_table(results: dict, shipped: dict | None) -> str:
    """The model alone (each checkpoint at its threshold) beside the shipped path, on all pairs and facades."""
    width = max([44] + [len(r.get("model", k)) for k, r in results.items()]
                + ([len(shipped["grader"]) + 14] if shipped else []))
    head = f"{'row':<{width}} {'scope':<7} {'pairs':>6} " + " ".join(f"{k:>13}" for k in FIGURES)
    lines = ["The model alone and the shipped grading path (model + evidence + user labels; stored grades), "
             f"all pairs and facades (<= {FACADE_MAX_HORIZONTAL:.0%} of a patch's faces horizontal)", head]
    rows = [(_row_name(k, r), r) for k, r in results.items()]
    if shipped:
        rows.append((f"shipped path: {shipped['grader']}", shipped))
    for name, r in rows:
        for scope in ("all", "facade"):
            rep = r.get(scope) or {}
            if rep:
                n = rep.get("n", 0)
                lines.append(f"{name:<{width}} {scope:<7} {n:>6} " + " ".join(f"{rep.get(k, np.nan):>13.4f}"
                                                                             for k in FIGURES))
    if not shipped:
        lines.append("(no stored grades: the campus was processed without classify, so no shipped-path row)")
    return "\n".join(lines)


def _result_key(name: str, kind: str, results: dict) -> str:
    """The key a checkpoint passed as ``name`` is reported under: ``name`` when it stands for the checkpoint's
    kind, else the kind itself (unless taken: then the name, which the tables show as a row of its kind);
    a key already taken gets a ``#n`` suffix, so no result is overwritten."""
    from ms3d_model.report import suite_kind

    key = name if suite_kind(name) == kind or kind in results else kind
    n = 2
    while key in results:  # two checkpoints under one name: both rows stay
        key, n = f"{name}#{n}", n + 1
    return key


def _cue_seconds_per_pair(work_dir: str, n: int = 256) -> float:
    """Wall seconds per pair of the hand-made cues (from raw pairs of the campus's first non-empty tile)."""
    from ms3d_model.cues import batch_cues
    from storage.workdir.layout import WorkDir
    from tasks.classify import read_tile_pairs

    for t in WorkDir(work_dir).live_tiles():
        tp = read_tile_pairs(WorkDir(work_dir).tile_dir(t), stream_points=True)  # reads only the pairs timed
        if len(tp) >= 16:
            idx = np.arange(min(n, len(tp)))
            pts, tris, _, oe = tp.raw(idx)
            t0 = time.perf_counter()
            batch_cues(pts, tris, oe, tp.keys[idx])
            return (time.perf_counter() - t0) / len(idx)
    return float("nan")


def suite_models(suite_dir: str) -> dict[str, str]:
    """{name: best.pt} of every trained network under a ``ms3d train --suite`` output folder."""
    return {p.parent.name: str(p) for p in sorted(Path(suite_dir).glob("*/best.pt"))}


__all__ = ["campus_rows", "evaluate", "forward_seconds", "held_out_campus", "path_table", "replace", "shipped_path_row",
           "suite_models"]
