"""Grouping rows by equal values: the sort-based kernel behind welding and de-duplication (pure numpy)."""

from __future__ import annotations

import numpy as np


def first_of_groups(*columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Group rows by equal values in all ``columns`` (each (r,) int64).

    Returns (group (r,) int64 numbered in lexicographic order of the values, first (g,) int64 index of
    the first row of each group).
    """
    order = np.lexsort(columns[::-1])  # lexsort is stable; its last key is the primary one
    new = np.zeros(len(order), bool)
    if len(order):
        new[0] = True
        for c in columns:
            sc = c[order]
            new[1:] |= sc[1:] != sc[:-1]
    group = np.empty(len(order), np.int64)
    group[order] = np.cumsum(new) - 1
    return group, order[new]
