"""The user's own labels (``WORKDIR/labels/*.csv``, written by ``ms3d view WORKDIR --label``) win over the
grader for the patches they name: a patch the user marked bad is repaired whatever its score, one marked
good is left alone whatever the model or the geometric evidence say.

A new label re-grades only its own tile (the classify record keeps a digest of the tile's labels, read by
:func:`storage.workdir.user_labels.tile_user_labels`) and repair then re-runs only the regions whose grades
changed.
"""

from __future__ import annotations

import hashlib

import numpy as np


def labels_digest(keys: np.ndarray, labels: np.ndarray) -> str | None:
    """16 hex digits naming a tile's labels (None when it has none, so records of unlabelled tiles keep
    the parameters they had before any label existed)."""
    if not len(keys):
        return None
    h = hashlib.sha256(np.asarray(keys, np.int64).tobytes() + np.asarray(labels, np.int8).tobytes())
    return h.hexdigest()[:16]


def apply_user_labels(patch_keys: np.ndarray, grade: np.ndarray, keys: np.ndarray,
                      labels: np.ndarray) -> np.ndarray:
    """(n,) int8: the user's label of each patch (n,) int64 it names, -1 elsewhere; ``grade`` (n,) int8 is set
    to the label in place for those patches (labels of patches the tile does not hold are ignored).

    >>> g = np.array([0, 1, -1], np.int8)
    >>> apply_user_labels(np.array([10, 11, 12]), g, np.array([11, 12, 99]), np.array([0, 1, 1], np.int8)).tolist(), g.tolist()
    ([-1, 0, 1], [0, 0, 1])
    """
    user = np.full(len(patch_keys), -1, np.int8)
    if len(keys) and len(patch_keys):
        pos = np.searchsorted(keys, patch_keys)
        pos = np.minimum(pos, len(keys) - 1)
        hit = keys[pos] == patch_keys
        user[hit] = labels[pos[hit]]
        grade[hit] = labels[pos[hit]]
    return user


__all__ = ["apply_user_labels", "labels_digest"]
