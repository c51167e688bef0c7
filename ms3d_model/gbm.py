"""The non-deep baseline: gradient-boosted trees on the hand-made pair cues (:mod:`ms3d_model.cues`).

scikit-learn's HistGradientBoostingClassifier (LightGBM-style histogram boosting), early stopping on an
inner 10 % of the training pairs. Timed like the networks: one pair's forward time is its cue extraction
(measured separately) plus the trees.
"""

from __future__ import annotations

import time

import numpy as np


def fit_gbm(cues: np.ndarray, labels: np.ndarray, seed: int = 0, max_iter: int = 500, learning_rate: float = 0.1,
            max_leaf_nodes: int = 31, l2: float = 0.0, balanced: bool = False):
    """A fitted classifier on (B, C) float32 cues and (B,) labels (0 good, 1 bad); early stopping after 20
    rounds without gain on an inner 10 %. ``balanced``: inverse-frequency class weights."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    clf = HistGradientBoostingClassifier(max_iter=max_iter, learning_rate=learning_rate, max_leaf_nodes=max_leaf_nodes,
                                         l2_regularization=l2, early_stopping=True, validation_fraction=0.1,
                                         n_iter_no_change=20, random_state=seed,
                                         class_weight="balanced" if balanced else None)
    clf.fit(np.asarray(cues, np.float32), np.asarray(labels, np.int64))
    return clf


def gbm_p_bad(clf, cues: np.ndarray) -> np.ndarray:
    """(B,) float32 probability of "bad"."""
    return clf.predict_proba(np.asarray(cues, np.float32))[:, 1].astype(np.float32)


def gbm_seconds_per_pair(clf, cues: np.ndarray, batch: int) -> float:
    """Wall seconds per pair of the trees alone at ``batch`` pairs per call (cue extraction not included)."""
    x = np.asarray(cues[:batch], np.float32)
    reps = max(1, 256 // len(x))
    t = time.perf_counter()
    for _ in range(reps):
        clf.predict_proba(x)
    return (time.perf_counter() - t) / (reps * len(x))


def tree_arrays(clf) -> dict[str, np.ndarray]:
    """A fitted binary HistGradientBoostingClassifier as padded arrays (T trees x M nodes): feature (int64),
    threshold (float32; left when x <= threshold), missing_left / is_leaf (bool), left / right (int64), value
    (float32 leaf values), baseline (1,) float32 raw score. Categorical splits are not used by fit_gbm."""
    trees = [p[0].nodes for p in clf._predictors]
    t, m = len(trees), max(len(n) for n in trees)
    out = {"feature": np.zeros((t, m), np.int64), "threshold": np.zeros((t, m), np.float32),
           "missing_left": np.zeros((t, m), bool), "is_leaf": np.ones((t, m), bool),
           "left": np.zeros((t, m), np.int64), "right": np.zeros((t, m), np.int64), "value": np.zeros((t, m), np.float32)}
    for i, n in enumerate(trees):
        k = len(n)
        out["feature"][i, :k] = n["feature_idx"]
        out["threshold"][i, :k] = n["num_threshold"]
        out["missing_left"][i, :k] = n["missing_go_to_left"].astype(bool)
        out["is_leaf"][i, :k] = n["is_leaf"].astype(bool)
        out["left"][i, :k] = n["left"]
        out["right"][i, :k] = n["right"]
        out["value"][i, :k] = n["value"]
    out["baseline"] = np.asarray(clf._baseline_prediction, np.float32).reshape(1)
    return out


def tree_depth(arrays: dict) -> int:
    """Levels to walk so that every tree reaches a leaf (number of nodes bounds it; the real depth is less)."""
    left, right, leaf = arrays["left"], arrays["right"], arrays["is_leaf"]
    depth = np.zeros(left.shape, np.int64)
    for _ in range(left.shape[1]):  # relax parent -> child depths until stable (a few passes in practice)
        t_idx = np.broadcast_to(np.arange(left.shape[0])[:, None], left.shape)
        new = depth.copy()
        inner = ~leaf
        np.maximum.at(new, (t_idx[inner], left[inner]), depth[inner] + 1)
        np.maximum.at(new, (t_idx[inner], right[inner]), depth[inner] + 1)
        if np.array_equal(new, depth):
            break
        depth = new
    return int(depth.max())
