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


def choose_threshold(labels: np.ndarray, p_bad: np.ndarray, min_precision: float = 0.80,
                     objective: str = "f1") -> dict:
    """The operating threshold on "bad" chosen on validation among the thresholds whose precision on bad
    reaches ``min_precision``: objective "f1" takes the largest F1 on bad, "recall" the largest recall (the
    lowest such threshold: repair can only fix what is flagged). When no threshold reaches the floor, the
    largest F1 overall (``floor_met`` False).

    labels: (n,) int (0 good, 1 bad); p_bad: (n,) float. Candidate thresholds are the distinct scores (a pair
    is bad when its score >= the threshold); ties go to the higher threshold (fewer repairs).
    Returns {"threshold", "precision", "recall", "f1", "floor_met", "min_precision", "objective"}; threshold
    0.5 and NaN figures when there is no bad pair.

    >>> y = np.array([0, 0, 1, 0, 1, 1]); p = np.array([.1, .2, .3, .6, .7, .9])
    >>> choose_threshold(y, p, 0.9)["threshold"], round(choose_threshold(y, p, 0.5)["f1"], 3)
    (0.7, 0.857)
    >>> y, p = np.array([1, 0, 0, 1, 1, 1]), np.array([.4, .5, .6, .7, .8, .9])
    >>> choose_threshold(y, p, 0.6, "f1")["threshold"], choose_threshold(y, p, 0.6, "recall")["threshold"]
    (0.7, 0.4)
    """
    if objective not in ("f1", "recall"):
        raise ValueError(f"threshold objective must be 'f1' or 'recall', got {objective!r}")
    y = np.asarray(labels).astype(bool)
    s = np.asarray(p_bad, np.float64)
    out = {"threshold": 0.5, "precision": float("nan"), "recall": float("nan"), "f1": float("nan"),
           "floor_met": False, "min_precision": float(min_precision), "objective": objective}
    n_pos = int(y.sum())
    if n_pos == 0:
        return out
    order = np.argsort(-s, kind="stable")
    s, y = s[order], y[order]
    last = np.r_[s[1:] != s[:-1], True]  # thresholds = distinct scores; predicted bad = everything up to here
    tp = np.cumsum(y)[last]
    k = np.flatnonzero(last) + 1
    thr = s[last]
    precision, recall = tp / k, tp / n_pos
    f1 = np.where(tp > 0, 2 * precision * recall / np.maximum(precision + recall, 1e-12), 0.0)
    ok = precision >= min_precision
    cand = np.flatnonzero(ok) if ok.any() else np.arange(len(thr))
    goal = recall if objective == "recall" and ok.any() else f1
    best = cand[np.argmax(goal[cand])]  # argmax takes the first maximum = the highest threshold
    out.update(threshold=float(thr[best]), precision=float(precision[best]), recall=float(recall[best]),
               f1=float(f1[best]), floor_met=bool(ok.any()))
    return out


SELECT_BY = ("ap_bad", "f1_bad", "map", "acc")


def selection_score(row: dict, by: str = "ap_bad") -> tuple[float, float]:
    """The key an epoch is ranked by (higher is better): (``row[by]``, ``row["ap_bad"]``) with NaN as -inf.
    ``by``: "ap_bad" (average precision on bad), "f1_bad" (F1 on bad at the chosen threshold), "map" or
    "acc" (the paper's choice, which rewards majority-class epochs)."""
    if by not in SELECT_BY:
        raise ValueError(f"unknown selection metric {by!r}; choose one of {SELECT_BY}")

    def num(v) -> float:
        v = float(v) if v is not None else float("nan")
        return -np.inf if np.isnan(v) else v

    return num(row.get(by)), num(row.get("ap_bad"))


def best_epoch(history: list[dict], by: str = "ap_bad") -> int:
    """Index into ``history`` (rows of per-epoch validation metrics) of the epoch ``by`` selects (first best).

    >>> best_epoch([{"acc": .8, "ap_bad": .3}, {"acc": .7, "ap_bad": .6}])
    1
    """
    if not history:
        raise ValueError("no epochs to select from")
    keys = [selection_score(h, by) for h in history]
    return max(range(len(keys)), key=lambda i: (keys[i], -i))
