"""``ms3d train --campus CONFIG --from CHECKPOINT``: adapt the grader to a user's own labels.

Reads the user's labels of the campus (``WORKDIR/labels/*.csv``, written by ``ms3d view WORKDIR --label``:
:mod:`storage.workdir.user_labels`), featurises those patches' pairs from the campus's stores, holds out a seeded
share of them (``holdout``) for validation, and mixes the rest with synth training pairs (the ``--seeds``
demo campuses and ``--work-dir`` labelled campuses, as ``ms3d train`` builds them: :func:`flows.train.load_pairs`).

- Trees (``gbm``, the shipped default): a refit on the synth training pairs plus the user's training pairs,
  each user pair repeated ``user_weight`` times (the trees' loss has no per-pair weight in
  :func:`ms3d_model.gbm.fit_gbm`; repetition is the same weighting). The threshold is chosen on the synth
  validation pairs only (area split with a buffer, as ``ms3d train``): the user's held-out pairs are
  never seen before they are scored.
- Networks: not yet (one clear error); ``ms3d_model.train.train_model`` starts from fresh weights.

When the user's campus is itself among the synth campuses (a labelled synth campus), its pairs at the
user-labelled patches are left out of the synth pairs, so the held-out user figures are not leaked.

Writes ``OUT/finetuned.pt``, ``OUT/MODEL_CARD.md`` (data, counts, figures on the held-out user labels for the
base and the fine-tuned model) and ``OUT/finetune.json``. Point ``classify.model`` at the checkpoint: the
classify stage re-grades (a new model hash), and repair re-runs only the regions whose patches changed.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from storage.errors import InputError

log = logging.getLogger("ms3d.finetune")


@dataclass
class FinetuneSpec:
    """campus: the campus YAML (its work dir holds the stores and labels/); base: the checkpoint to start from;
    seeds / work_dirs / data: the synth pairs to mix in (as :class:`flows.train.TrainSpec`)."""

    campus: str
    base: str
    out: str
    seeds: list = field(default_factory=lambda: [7, 11])
    work_dirs: list[str] = field(default_factory=list)
    data: str = "ms3d-work"
    holdout: float = 0.25
    user_weight: int = 10
    block_m: float = 20.0
    seed: int = 0


def user_pairs(work_dir: str | Path, name: str, prof):
    """The user's labelled patches of a processed campus as a PairSet (labels = the user's), and the number
    of labelled patches dropped because they are not gradable pairs (no faces or no points)."""
    from ms3d_model.dataset import PairSet
    from storage.grid import PatchGrid
    from storage.workdir.layout import WorkDir
    from storage.workdir.user_labels import read_user_labels
    from tasks.classify import featurise_tile_pairs, read_tile_pairs

    keys, labels = read_user_labels(work_dir)
    if not len(keys):
        raise InputError(Path(work_dir) / "labels", "no user labels (label patches with `ms3d view WORKDIR --label`)")
    wd = WorkDir(work_dir)
    parts, found = [], 0
    for t in wd.live_tiles():
        tp = read_tile_pairs(wd.tile_dir(t))
        idx = np.flatnonzero(np.isin(tp.keys, keys))
        if not len(idx):
            continue
        f, c = featurise_tile_pairs(tp, idx, prof.max_points, prof.max_faces, prof.k_centre, prof.seed)
        lab = labels[np.searchsorted(keys, tp.keys[idx])]
        parts.append(PairSet(f, c, lab, tp.ijk[idx], np.zeros(len(idx), np.int16), (name,)).compact())
        found += len(idx)
    if not parts:
        raise InputError(Path(work_dir) / "labels", f"none of the {len(keys)} labelled patches is a gradable pair "
                                                    f"(first: {PatchGrid.unpack(keys[:1])[0].tolist()})")
    return PairSet.concat(parts), len(keys) - found


def _users_own(synth, campuses: dict[str, str], work_dir: str, users) -> np.ndarray:
    """(B,) bool: synth pairs of the user's own campus (a labelled synth campus can be both) at patches the
    user labelled; they are left out so the held-out user labels never leak into training."""
    from storage.grid import PatchGrid

    own = [n for n, w in campuses.items() if Path(w).resolve() == Path(work_dir).resolve()]
    if not own or not len(synth):
        return np.zeros(len(synth), bool)
    in_own = np.isin(np.asarray(synth.names)[synth.campus], own)
    return in_own & np.isin(PatchGrid.pack(synth.ijk), PatchGrid.pack(users.ijk))


def _figures(labels: np.ndarray, p_bad: np.ndarray, threshold: float) -> dict:
    y, pred = np.asarray(labels) == 1, np.asarray(p_bad) >= threshold
    tp = int((y & pred).sum())
    return {"n": len(y), "n_bad": int(y.sum()), "acc": float((y == pred).mean()) if len(y) else float("nan"),
            "precision_bad": tp / max(int(pred.sum()), 1), "recall_bad": tp / max(int(y.sum()), 1),
            "threshold": float(threshold)}


def _split(n: int, share: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(train, held-out) index arrays: a seeded ``share`` of n held out (at least 1 when n > 1)."""
    order = np.random.default_rng(seed).permutation(n)
    k = min(max(round(share * n), 1 if n > 1 else 0), n - 1) if n > 1 else 0
    return np.sort(order[k:]), np.sort(order[:k])


def finetune(spec: FinetuneSpec) -> dict:
    """Fine-tune ``spec.base`` on the campus's user labels; returns the summary written to finetune.json."""
    from flows.train import campus_variant, load_pairs, prepare_campus
    from ms3d_model.dataset import PairSet, area_split
    from ms3d_model.train import checkpoint_threshold, load_checkpoint, predict
    from tasks.config import CampusConfig

    t0 = time.perf_counter()
    cfg = CampusConfig.from_yaml(spec.campus)
    try:
        base_net, prof, meta = load_checkpoint(spec.base)
    except FileNotFoundError:
        raise InputError(spec.base, "checkpoint not found") from None
    except (ValueError, RuntimeError) as exc:
        raise InputError(spec.base, f"not a loadable checkpoint ({exc})") from None
    if prof.net.arch != "gbm":
        raise InputError(spec.base, f"fine-tuning a {prof.net.arch!r} network is not supported yet (trees only)")
    users, dropped = user_pairs(cfg.work_dir, "user", prof)
    u_tr, u_va = _split(len(users), spec.holdout, spec.seed)
    campuses = {campus_variant(s)[3]: prepare_campus(s, spec.data) for s in spec.seeds}
    campuses.update({Path(w).name: w for w in spec.work_dirs})
    if not campuses:
        raise InputError(spec.campus, "no synth pairs to mix with: give --seeds or --work-dir")
    synth = load_pairs(campuses, prof, str(Path(spec.data) / "cache"))
    excluded = _users_own(synth, campuses, cfg.work_dir, users)
    synth = synth.take(np.flatnonzero(~excluded))
    size = np.asarray(cfg.grid().size_m, np.float64)
    s_tr, s_va = area_split(synth.ijk, size, synth.campus, spec.block_m, 0.2, prof.seed, 0.0)
    tr = PairSet.concat([synth.take(np.flatnonzero(s_tr))] + [users.take(u_tr)] * max(spec.user_weight, 1))
    va = synth.take(np.flatnonzero(s_va))  # the threshold is chosen here: the held-out user pairs stay unseen
    from flows.train import fit_tree_model

    out = Path(spec.out)
    t_fit = time.perf_counter()
    prof = replace(prof, name=f"{prof.name}:finetune", net=replace(prof.net, n_cues=int(tr.cues.shape[1])))
    res = fit_tree_model(prof, tr, va, out)  # the current cue set: older trees read its leading columns
    fit_seconds = time.perf_counter() - t_fit
    best = out / "finetuned.pt"
    Path(res["best_path"]).replace(best)
    new_net, _, new_meta = load_checkpoint(best)
    held = users.take(u_va)
    figs = {"base": _figures(held.labels, predict(base_net, held, 1024), checkpoint_threshold(meta)),
            "finetuned": _figures(held.labels, predict(new_net, held, 1024), checkpoint_threshold(new_meta))}
    summary = {"campus": str(spec.campus), "work_dir": str(cfg.work_dir), "base": str(spec.base),
               "checkpoint": str(best), "model_hash": res["model_hash"], "synth_campuses": campuses,
               "n_user_labels": len(users) + dropped, "n_user_dropped_not_pairs": dropped,
               "n_user_train": len(u_tr), "n_user_heldout": len(u_va), "user_weight": spec.user_weight,
               "n_synth_excluded_user_patches": int(excluded.sum()), "n_synth_train": int(s_tr.sum()), "n_synth_val": int(s_va.sum()), "validation": res["best"],
               "heldout_user": figs, "fit_seconds": fit_seconds, "wall_seconds": time.perf_counter() - t0}
    (out / "finetune.json").write_text(json.dumps(summary, indent=1, default=str))
    (out / "MODEL_CARD.md").write_text(model_card(summary))
    log.info("fine-tuned %s -> %s in %.1f s", spec.base, best, summary["wall_seconds"])
    return summary


def model_card(s: dict) -> str:
    """The MODEL_CARD.md text of a fine-tune summary."""
    v, h = s["validation"], s["heldout_user"]

    def row(name, f):
        return (f"| {name} | {f['n']} ({f['n_bad']} bad) | {100 * f['acc']:.1f} % | {f['precision_bad']:.3f} | "
                f"{f['recall_bad']:.3f} | {f['threshold']:.3f} |")

    return "\n".join([
        "# Fine-tuned grader (gradient-boosted trees)", "",
        f"- base checkpoint: `{s['base']}`; this checkpoint: `{Path(s['checkpoint']).name}` (sha256 {s['model_hash'][:16]}…)",
        f"- campus: `{s['campus']}` (work dir `{s['work_dir']}`)",
        (f"- user labels: {s['n_user_labels']} patches from `labels/*.csv` ({s['n_user_dropped_not_pairs']} dropped: "
        f"not gradable pairs); {s['n_user_train']} trained on, each counted {s['user_weight']} times; "
        f"{s['n_user_heldout']} held out"),
        (f"- synth pairs: {s['n_synth_train']} train, {s['n_synth_val']} validation (area split) from "
        f"{', '.join(sorted(s['synth_campuses']))}"),
        (f"- validation (synth validation + held-out user pairs, threshold chosen there): AP(bad) {v['ap_bad']:.3f}, "
        f"mAP {v['map']:.3f}, threshold {v['threshold']:.3f}, precision {v['precision_bad']:.3f}, "
        f"recall {v['recall_bad']:.3f}"), "",
        "Held-out user labels (never trained on), each model at its own threshold:", "",
        "| model | pairs | accuracy | precision (bad) | recall (bad) | threshold |", "|---|---|---|---|---|---|",
        row("base", h["base"]), row("fine-tuned", h["finetuned"]), "",
        (f"Fine-tune wall time: {s['wall_seconds']:.1f} s (trees {s['fit_seconds']:.1f} s). Few held-out labels make "
        "these figures noisy: read them as a sanity check, not as an accuracy."), ""])
