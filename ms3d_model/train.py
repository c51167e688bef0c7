"""Training and inference of a network on :class:`~ms3d_model.dataset.PairSet` s: per-epoch metrics, PNG
curves, checkpoints that load with ``torch.load(weights_only=True)``.

Training (defaults in :mod:`ms3d_model.profiles`, objectives in :mod:`ms3d_model.objectives`): the pairs are
held as tensors once (:class:`~ms3d_model.dataset.PairTensors`); each epoch draws ``pairs_per_epoch`` of
them; after each epoch the validation pairs are scored, the operating threshold is chosen on them
(:func:`~ms3d_model.metrics.choose_threshold`: the largest recall (or F1) on bad at precision >= ``min_precision``), and the
epoch that ``select_by`` ranks first (validation AP on bad by default) is kept as ``best.pt``.

A checkpoint is a plain dict: ``{"format": "ms3d-model/1", "profile": Profile.to_json(), "state_dict": ...,
"metrics": {...}, "history": [...], "threshold": float}`` (tensors, strings, numbers, lists and dicts only);
``threshold`` is the operating point the classify stage grades at (:func:`checkpoint_threshold`: 0.5 for
checkpoints written before it existed).
"""

from __future__ import annotations

import hashlib
import json
import logging
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from torch import nn

from .cues import N_CUES
from .dataset import PairSet, PairTensors, batches, to_batch
from .metrics import best_epoch, choose_threshold, classification_report
from .net import build_net, kernel_response_stats, n_parameters
from .objectives import make_criterion, make_optimiser
from .profiles import Profile

log = logging.getLogger("ms3d.model")
FORMAT = "ms3d-model/1"
DEFAULT_THRESHOLD = 0.5


def set_seeds(seed: int) -> None:
    torch.manual_seed(seed)  # every device's generator
    np.random.seed(seed % (2**32))


def resolve_device(name: str = "auto") -> torch.device:
    """The torch device of a profile's ``device`` field: "auto" (CUDA when present, else the CPU), "cpu",
    "cuda" or "cuda:N". Asking for CUDA where there is none is an error saying so.

    >>> resolve_device("cpu").type
    'cpu'
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(name)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {name!r} asked for, but this torch ({torch.__version__}) sees no CUDA device")
    return dev


def net_device(net: nn.Module) -> torch.device:
    """The device a module's parameters (or buffers) live on; the CPU for one without any."""
    for t in list(net.parameters()) + list(net.buffers()):
        return t.device
    return torch.device("cpu")


def to_device(batch: dict[str, torch.Tensor], device: torch.device) -> dict[str, torch.Tensor]:
    """A batch dict with every tensor moved to ``device`` (unchanged on the CPU)."""
    if device.type == "cpu":
        return batch
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def make_model(profile: Profile, cues: np.ndarray | None = None) -> nn.Module:
    """A fresh network of ``profile``; for MS3DQE-Net+ the cue standardisation comes from ``cues`` (B, C)."""
    net = build_net(profile.net)
    if profile.net.n_cues and cues is not None and len(cues):
        cues = cues[:, :profile.net.n_cues]  # a network of an older, shorter cue set reads the leading columns
        mean = np.nanmean(cues, axis=0)
        std = np.maximum(np.nanstd(cues, axis=0), 1e-6)
        net.cue_mean.copy_(torch.from_numpy(mean.astype(np.float32)))
        net.cue_std.copy_(torch.from_numpy(std.astype(np.float32)))
    return net


def predict(net: nn.Module, ps: PairSet, batch_size: int = 64) -> np.ndarray:
    """(B,) float32 probability of "bad" for each pair (eval mode, no gradients)."""
    net.eval()
    out = np.empty(len(ps), np.float32)
    dev = net_device(net)
    with torch.inference_mode():
        for idx in batches(len(ps), batch_size, shuffle=False):
            logits = net(to_device(to_batch(ps.feats.take(idx), ps.cues[idx] if net_uses_cues(net) else None), dev))
            out[idx] = torch.softmax(logits, dim=1)[:, 1].cpu().numpy()
    return out


def predict_tensors(net: nn.Module, pt: PairTensors, batch_size: int = 64) -> np.ndarray:
    """(B,) float32 probability of "bad" for each pair of ``pt`` (eval mode, no gradients)."""
    net.eval()
    out = np.empty(len(pt), np.float32)
    cues, dev = net_uses_cues(net), net_device(net)
    with torch.inference_mode():
        for idx in batches(len(pt), batch_size, shuffle=False):
            out[idx] = torch.softmax(net(to_device(pt.batch(idx, cues), dev)), dim=1)[:, 1].cpu().numpy()
    return out


def net_uses_cues(net: nn.Module) -> bool:
    return bool(getattr(net, "cfg", None) is not None and net.cfg.n_cues)


class _Bar:
    """A one-line progress bar on stderr (a terminal), or a log line every ~10 % elsewhere."""

    def __init__(self, total: int, label: str, enabled: bool):
        self.total, self.label, self.enabled = total, label, enabled
        self.tty = enabled and sys.stderr.isatty()
        self.done, self.t0, self.next_log = 0, time.perf_counter(), 0.1

    def update(self, n: int, loss: float) -> None:
        self.done += n
        if not self.enabled:
            return
        frac = self.done / max(self.total, 1)
        rate = self.done / max(time.perf_counter() - self.t0, 1e-9)
        text = f"{self.label} {self.done}/{self.total} pairs {rate:.1f}/s loss {loss:.4f}"
        if self.tty:
            bar = "#" * int(30 * frac)
            sys.stderr.write(f"\r[{bar:<30}] {text}")
            if self.done >= self.total:
                sys.stderr.write("\n")
            sys.stderr.flush()
        elif frac >= self.next_log:
            log.info(text)
            self.next_log += 0.1


def save_checkpoint(path: str | Path, net: nn.Module, profile: Profile, metrics: dict | None = None,
                    history: list | None = None, threshold: float | None = None) -> str:
    """Write a checkpoint atomically; returns its sha256 (the model hash). threshold: the operating point on
    the probability of bad (None: :data:`DEFAULT_THRESHOLD`)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().clone() for k, v in net.state_dict().items()}  # loads on any machine
    thr = DEFAULT_THRESHOLD if threshold is None else float(threshold)
    if not 0.0 <= thr <= 1.0:
        raise ValueError(f"threshold {thr} is not a probability")
    obj = {"format": FORMAT, "profile": profile.to_json(), "state_dict": state,
           "metrics": json.loads(json.dumps(metrics or {})), "history": json.loads(json.dumps(history or [])),
           "threshold": thr}
    tmp = path.with_name(f".{path.name}.tmp")
    torch.save(obj, tmp)
    tmp.replace(path)
    return model_hash(path)


def model_hash(path: str | Path) -> str:
    """sha256 of a checkpoint file (the identity classify records and fingerprints)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def load_checkpoint(path: str | Path) -> tuple[nn.Module, Profile, dict]:
    """(network in eval mode, profile, the checkpoint dict without the weights); ``weights_only=True``."""
    obj = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(obj, dict) or obj.get("format") != FORMAT:
        raise ValueError(f"{path}: not an ms3d model checkpoint (format {obj.get('format') if isinstance(obj, dict) else None!r})")
    profile = Profile.from_json(obj["profile"])
    net = build_net(profile.net, obj["state_dict"])
    net.load_state_dict(obj["state_dict"])
    net.eval()
    return net, profile, {k: v for k, v in obj.items() if k != "state_dict"}


def checkpoint_threshold(meta: dict) -> float:
    """The operating threshold a checkpoint ships (``meta``: the dict :func:`load_checkpoint` returns);
    :data:`DEFAULT_THRESHOLD` for checkpoints written before thresholds were stored."""
    return float(meta.get("threshold", DEFAULT_THRESHOLD))


def save_curves(history: list[dict], path: str | Path, title: str = "") -> None:
    """Loss and accuracy per epoch (train and validation) as a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = [h["epoch"] for h in history]
    fig, ax = plt.subplots(1, 2, figsize=(10, 4))
    ax[0].plot(ep, [h["train_loss"] for h in history], "o-", label="train")
    ax[0].plot(ep, [h["val_loss"] for h in history], "o-", label="validation")
    ax[0].set_xlabel("epoch"), ax[0].set_ylabel("cross-entropy"), ax[0].legend()
    ax[1].plot(ep, [h["train_acc"] for h in history], "o-", label="train")
    ax[1].plot(ep, [h["val_acc"] for h in history], "o-", label="validation")
    ax[1].plot(ep, [h["val_map"] for h in history], "s--", label="validation mAP")
    ax[1].plot(ep, [h.get("val_ap_bad", np.nan) for h in history], "^--", label="validation AP bad")
    ax[1].plot(ep, [h.get("val_recall_bad", np.nan) for h in history], "v:", label="recall bad @ threshold")
    ax[1].set_xlabel("epoch"), ax[1].set_ylabel("accuracy / AP / recall"), ax[1].legend()
    fig.suptitle(title)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _loss_on(labels: np.ndarray, p_bad: np.ndarray) -> float:
    p = np.clip(np.where(labels == 1, p_bad, 1 - p_bad), 1e-7, 1.0)
    return float(-np.log(p).mean()) if len(p) else float("nan")


def validation_row(labels: np.ndarray, p_bad: np.ndarray, min_precision: float,
                   objective: str = "f1") -> tuple[dict, dict]:
    """(the epoch's validation figures for the history, the report at the chosen threshold for the checkpoint).

    History keys: val_loss, val_acc (at 0.5, the paper's), val_map, val_ap_bad, threshold, val_acc_at_threshold,
    val_precision_bad, val_recall_bad, val_f1_bad (at the threshold chosen on these pairs)."""
    labels = np.asarray(labels)
    at_half = classification_report(labels, p_bad)
    choice = choose_threshold(labels, p_bad, min_precision, objective)
    rep = classification_report(labels, p_bad, choice["threshold"]) | {"threshold": choice["threshold"],
                                                                        "precision_floor_met": choice["floor_met"],
                                                                        "min_precision": min_precision,
                                                                        "threshold_objective": objective,
                                                                        "acc_at_0.5": at_half["acc"]}
    row = {"val_loss": _loss_on(labels, p_bad), "val_acc": at_half["acc"], "val_map": rep["map"],
           "val_ap_bad": rep["ap_bad"], "threshold": choice["threshold"], "val_acc_at_threshold": rep["acc"],
           "val_precision_bad": rep["precision_bad"], "val_recall_bad": rep["recall_bad"], "val_f1_bad": rep["f1_bad"]}
    return row, rep


def selection_view(row: dict) -> dict:
    """A history row under the names :func:`ms3d_model.metrics.best_epoch` ranks by."""
    return {"ap_bad": row.get("val_ap_bad"), "f1_bad": row.get("val_f1_bad"), "map": row.get("val_map"),
            "acc": row.get("val_acc")}


def _train_epoch(net, data: PairTensors, pick: np.ndarray, profile: Profile, opt, step_sched, crit,
                 gen: torch.Generator, bar: _Bar) -> tuple[float, float, int]:
    """One pass over ``pick`` (indices into ``data``) in batches; (mean loss, accuracy at argmax, pairs)."""
    net.train()
    uses_cues, dev = net_uses_cues(net), net_device(net)
    loss_sum, correct, seen = 0.0, 0, 0
    for idx in batches(len(pick), profile.batch_size, shuffle=False):
        sel = pick[idx]
        y = data.tensors["labels"][torch.from_numpy(sel)].to(dev)
        logits = net(to_device(data.batch(sel, uses_cues, profile.noise_m, gen), dev))
        loss = crit(logits, y)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if step_sched is not None:
            step_sched.step()
        loss_sum += float(loss.detach()) * len(sel)
        correct += int((logits.argmax(1) == y).sum())
        seen += len(sel)
        bar.update(len(sel), loss_sum / seen)
    return loss_sum / max(seen, 1), correct / max(seen, 1), seen


def train_model(profile: Profile, train: PairSet, val: PairSet, out_dir: str | Path, progress: bool = True,
                on_epoch: Callable[[dict], None] | None = None) -> dict:
    """Train ``profile``'s network on ``train``, validate on ``val`` each epoch.

    Writes ``out_dir/last.pt``, ``out_dir/best.pt`` (the epoch ``profile.select_by`` ranks first, with the
    threshold chosen on validation at that epoch), ``out_dir/curves.png`` and ``out_dir/history.json``.
    Returns {"best": metrics of the best epoch at its threshold, "history": [...], "parameters",
    "train_seconds", "train_cpu_seconds", "best_path", "model_hash", "threshold", "kernel_stats_init"}.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(profile.threads)
    set_seeds(profile.seed)
    if profile.net.n_cues and profile.net.n_cues > N_CUES:
        raise ValueError(f"profile expects {profile.net.n_cues} cues, the featuriser makes {N_CUES}")
    device = resolve_device(profile.device)
    net = make_model(profile, train.cues).to(device)
    rng, gen = np.random.default_rng(profile.seed), torch.Generator().manual_seed(profile.seed)  # noise: on the CPU
    history, best = [], {}
    t_wall, t_cpu = time.perf_counter(), time.process_time()
    if profile.val_pairs and len(val) > profile.val_pairs:
        val = val.take(np.sort(np.random.default_rng(profile.seed + 1).permutation(len(val))[:profile.val_pairs]))
    data, val_t = PairTensors.from_pairs(train), PairTensors.from_pairs(val)
    n_per_epoch = min(profile.pairs_per_epoch or len(train), len(train))
    n_per_epoch -= n_per_epoch % profile.batch_size  # BatchNorm needs > 1 sample: whole batches only
    opt, sched, per_step = make_optimiser(profile, net.parameters(), profile.epochs * (n_per_epoch // profile.batch_size))
    crit = make_criterion(profile.loss, train.labels, profile.focal_gamma).to(device)
    log.info("training %s on %s: %d parameters, %d train / %d val pairs (%.1f %% / %.1f %% bad), %d pairs per epoch, "
             "%s + %s, loss %s, selection by %s", profile.name, device, n_parameters(net), len(train), len(val),
             100 * float(np.mean(train.labels == 1)), 100 * float(np.mean(val.labels == 1)), n_per_epoch,
             profile.optimizer, profile.schedule, crit, profile.select_by)
    kc = (kernel_response_stats(net, to_device(data.batch(np.arange(min(64, len(train)))), device), sigmas=(0.005, None))
          if len(train) else {})
    for name, st in kc.items():
        log.info("kernel correlation %s at init: mean %.3g, median %.3g, %.1f%% > 1e-3", name, st["mean"],
                 st["median"], 100 * st["frac_gt_1e-3"])
    for epoch in range(1, profile.epochs + 1):
        t_ep = time.perf_counter()
        bar = _Bar(n_per_epoch, f"epoch {epoch}/{profile.epochs}", progress)
        loss, acc, seen = _train_epoch(net, data, rng.permutation(len(train))[:n_per_epoch], profile, opt,
                                       sched if per_step else None, crit, gen, bar)
        if not per_step:
            sched.step()
        vrow, rep = validation_row(val.labels, predict_tensors(net, val_t, profile.eval_batch), profile.min_precision,
                                     profile.threshold_objective)
        row = {"epoch": epoch, "train_loss": loss, "train_acc": acc, **vrow, "lr": opt.param_groups[0]["lr"],
               "epoch_seconds": time.perf_counter() - t_ep, "pairs_per_s": seen / max(time.perf_counter() - t_ep, 1e-9)}
        history.append(row)
        log.info("epoch %d: train loss %.4f | val loss %.4f acc@0.5 %.4f mAP %.4f AP(bad) %.4f | threshold %.3f: "
                 "P %.3f R %.3f F1 %.3f | %.0f s", epoch, loss, row["val_loss"], row["val_acc"], row["val_map"],
                 row["val_ap_bad"], row["threshold"], row["val_precision_bad"], row["val_recall_bad"],
                 row["val_f1_bad"], row["epoch_seconds"])
        save_checkpoint(out_dir / "last.pt", net, profile, rep | {"epoch": epoch}, history, row["threshold"])
        if best_epoch([selection_view(h) for h in history], profile.select_by) == len(history) - 1:
            best = {**rep, "epoch": epoch}
            save_checkpoint(out_dir / "best.pt", net, profile, best, history, row["threshold"])
        save_curves(history, out_dir / "curves.png", f"{profile.name}: {profile.net.arch}")
        (out_dir / "history.json").write_text(json.dumps(history, indent=1))
        if on_epoch is not None:
            on_epoch(row)
        if profile.time_budget_s and time.perf_counter() - t_wall > profile.time_budget_s:
            log.info("time budget of %.0f s reached after epoch %d", profile.time_budget_s, epoch)
            break
    return {"best": best, "history": history, "parameters": n_parameters(net), "device": str(device),
            "train_seconds": time.perf_counter() - t_wall, "train_cpu_seconds": time.process_time() - t_cpu,
            "best_path": str(out_dir / "best.pt"), "model_hash": model_hash(out_dir / "best.pt"),
            "threshold": best.get("threshold", DEFAULT_THRESHOLD), "kernel_stats_init": kc}
