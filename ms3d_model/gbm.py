"""The non-deep baseline: gradient-boosted trees on the hand-made pair cues (:mod:`ms3d_model.cues`).

scikit-learn's HistGradientBoostingClassifier (LightGBM-style histogram boosting), early stopping on an
inner 10 % of the training pairs. Timed like the networks: one pair's forward time is its cue extraction
(measured separately) plus the trees.
"""

from __future__ import annotations

import time

import numpy as np


def fit_gbm(cues: np.ndarray, labels: np.ndarray, seed: int = 0, max_iter: int = 500):
    """A fitted classifier on (B, C) float32 cues and (B,) labels (0 good, 1 bad)."""
    from sklearn.ensemble import HistGradientBoostingClassifier

    clf = HistGradientBoostingClassifier(max_iter=max_iter, learning_rate=0.1, max_leaf_nodes=31,
                                         early_stopping=True, validation_fraction=0.1, n_iter_no_change=20,
                                         random_state=seed)
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
