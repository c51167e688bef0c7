"""What training optimises and how: the class-balanced loss, focal loss, and the optimiser + schedule.

- ``loss="balanced"`` (default): cross-entropy weighted by inverse class frequency on the training pairs, so
  good and bad carry equal total weight (the synth campuses are ~20-25 % bad and an unweighted loss parks
  the network at the majority class); ``"focal"``: focal loss (Lin et al. 2017) with the same class weights
  as alpha; ``"ce"``: the paper's plain cross-entropy.
- ``optimizer="adamw"`` + ``schedule="onecycle"`` (default): AdamW, one-cycle learning rate peaking at
  ``lr`` (per optimiser step, so sampled epochs still anneal to ~0); ``optimizer="sgd"`` +
  ``schedule="multistep"``: the paper's §4.4 (SGD, momentum 0.9, MultiStepLR at ``milestones``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

LOSSES = ("balanced", "focal", "ce")


def class_weights(labels: np.ndarray, n_classes: int = 2) -> np.ndarray:
    """(n_classes,) float32 inverse-frequency weights over labels >= 0, normalised so that sum_c w_c * n_c = n
    (the mean weight per pair is 1); an absent class gets weight 1 (and a lone class too).

    >>> [round(float(w), 4) for w in class_weights(np.array([0, 0, 0, 1]))]
    [0.6667, 2.0]
    """
    y = np.asarray(labels).astype(np.int64)
    counts = np.bincount(y[y >= 0], minlength=n_classes).astype(np.float64)
    n = counts.sum()
    present = max(int((counts > 0).sum()), 1)
    w = np.where(counts > 0, n / (present * np.maximum(counts, 1)), 1.0)
    return w.astype(np.float32)


class FocalLoss(nn.Module):
    """Mean over the batch of -w_y (1 - p_y)^gamma log p_y; logits (B, C) float32, targets (B,) int64.
    gamma 0 is weighted cross-entropy (normalised by the batch size, not by the weights)."""

    def __init__(self, weight: torch.Tensor | None = None, gamma: float = 2.0):
        super().__init__()
        self.gamma = float(gamma)
        self.register_buffer("weight", weight if weight is not None else torch.ones(2))

    def forward(self, logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        logp = F.log_softmax(logits, dim=1).gather(1, target[:, None])[:, 0]
        return (-self.weight[target] * (1 - logp.exp()).pow(self.gamma) * logp).mean()

    def __repr__(self) -> str:
        return f"FocalLoss(weight={self.weight.tolist()}, gamma={self.gamma})"


def make_criterion(loss: str, labels: np.ndarray, focal_gamma: float = 2.0) -> nn.Module:
    """The training loss ``loss`` (one of :data:`LOSSES`), weighted from the training ``labels`` (B,)."""
    if loss not in LOSSES:
        raise ValueError(f"unknown loss {loss!r}; choose one of {LOSSES}")
    if loss == "ce":
        return nn.CrossEntropyLoss()
    w = torch.from_numpy(class_weights(labels))
    return nn.CrossEntropyLoss(weight=w) if loss == "balanced" else FocalLoss(w, focal_gamma)


def make_optimiser(profile, params, total_steps: int):
    """(optimizer, scheduler, step_per_batch) for ``profile`` (fields optimizer, schedule, lr, momentum,
    weight_decay, milestones, gamma); ``total_steps``: optimiser steps of the whole run (one-cycle)."""
    if profile.optimizer == "adamw":
        opt = torch.optim.AdamW(params, lr=profile.lr, weight_decay=profile.weight_decay)
    elif profile.optimizer == "sgd":
        opt = torch.optim.SGD(params, lr=profile.lr, momentum=profile.momentum, weight_decay=profile.weight_decay)
    else:
        raise ValueError(f"unknown optimizer {profile.optimizer!r}; choose adamw or sgd")
    if profile.schedule == "onecycle":
        return opt, torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=profile.lr, total_steps=max(total_steps, 2),
                                                        pct_start=0.3), True
    if profile.schedule == "multistep":
        return opt, torch.optim.lr_scheduler.MultiStepLR(opt, milestones=list(profile.milestones),
                                                         gamma=profile.gamma), False
    raise ValueError(f"unknown schedule {profile.schedule!r}; choose onecycle or multistep")
