"""Classification metrics of the paper's tables: accuracy, mAP (mean over the two classes of the average
precision), per-class precision / recall / F1 and the confusion matrix.

Labels are 0 good, 1 bad; ``p_bad`` is the predicted probability of "bad" (the grade's score).
"""

from __future__ import annotations

import numpy as np


def average_precision(positive: np.ndarray, score: np.ndarray) -> float:
    """Area under the step-wise precision-recall curve (ranking by ``score`` descending; tied scores form
    one step). positive: (n,) bool. NaN when there is no positive.

    >>> round(average_precision(np.array([1, 0, 1, 0], bool), np.array([.9, .8, .7, .1])), 4)
    0.8333
    """
    positive = np.asarray(positive, bool)
    n_pos = int(positive.sum())
    if n_pos == 0:
        return float("nan")
    order = np.argsort(-np.asarray(score, np.float64), kind="stable")
    s, y = np.asarray(score, np.float64)[order], positive[order]
    tp = np.cumsum(y)
    last = np.r_[s[1:] != s[:-1], True]  # the last element of each run of equal scores
    tp, k = tp[last], np.flatnonzero(last) + 1
    precision, recall = tp / k, tp / n_pos
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


def classification_report(labels: np.ndarray, p_bad: np.ndarray, threshold: float = 0.5) -> dict:
    """Acc, mAP, per-class P/R/F1 and the 2x2 confusion matrix (rows truth good/bad, columns predicted)."""
    y = np.asarray(labels).astype(np.int64)
    p = np.asarray(p_bad, np.float64)
    pred = (p >= threshold).astype(np.int64)
    cm = np.zeros((2, 2), np.int64)
    np.add.at(cm, (y, pred), 1)
    out = {"n": len(y), "acc": float((pred == y).mean()) if len(y) else float("nan"),
           "ap_good": average_precision(y == 0, 1 - p), "ap_bad": average_precision(y == 1, p),
           "confusion": cm.tolist()}
    out["map"] = float(np.nanmean([out["ap_good"], out["ap_bad"]]))
    for c, name in ((0, "good"), (1, "bad")):
        tp = cm[c, c]
        prec = tp / cm[:, c].sum() if cm[:, c].sum() else float("nan")
        rec = tp / cm[c, :].sum() if cm[c, :].sum() else float("nan")
        f1 = 2 * prec * rec / (prec + rec) if (prec + rec) > 0 else float("nan")
        out[f"precision_{name}"], out[f"recall_{name}"], out[f"f1_{name}"] = float(prec), float(rec), float(f1)
    return out
