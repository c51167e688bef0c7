"""Neighbourhood cues: a pair's cues seen next to its neighbours' in the same tile.

A defect (a hole, a misaligned storey, a recess) covers several patch cells, and the cells at its rim carry
weak evidence of their own. What their neighbours show is the strongest extra cue the trees found (+0.025
validation AP on the demo campuses). The neighbourhood is the 26 cells around a pair's cell that hold a pair
of the **same tile**: classify grades a tile at a time, and training builds its pairs per tile the same way,
so the cue means the same in both. Cells at a tile's border see fewer neighbours (``nb_count`` says so).
"""

from __future__ import annotations

import numpy as np

from .cues import CONTEXT_CUE_NAMES, CONTEXT_SOURCES, PAIR_CUE_NAMES

_SOURCE_COLS = np.array([PAIR_CUE_NAMES.index(n) for n in CONTEXT_SOURCES])
_OFFSETS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)])


def _cell_keys(ijk: np.ndarray) -> np.ndarray:
    """(P,) int64 keys of (P, 3) cells, unique for |i|, |j|, |k| < 2**20."""
    o = (np.asarray(ijk, np.int64) + (1 << 20)) & ((1 << 21) - 1)
    return (o[:, 0] << 42) | (o[:, 1] << 21) | o[:, 2]


def context_cues(pair_cues: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """(P, len(CONTEXT_CUE_NAMES)) float32: per pair, the max and the mean of the :data:`CONTEXT_SOURCES` cues
    over the pairs in its 26 neighbouring cells, then their count. 0 where a pair has no neighbour.

    pair_cues: (P, >= N_PAIR_CUES) float cues of the pairs of one tile (:data:`PAIR_CUE_NAMES` order);
    ijk: (P, 3) int patch cells of the pairs (one pair per cell).

    >>> cues = np.zeros((3, len(PAIR_CUE_NAMES))); cues[:, PAIR_CUE_NAMES.index("p2m_p90")] = [0.1, 0.5, 9.0]
    >>> c = dict(zip(CONTEXT_CUE_NAMES, context_cues(cues, np.array([[0, 0, 0], [1, 1, 0], [5, 0, 0]])).T))
    >>> c["nb_max_p2m_p90"].tolist(), c["nb_count"].tolist()
    ([0.5, 0.10000000149011612, 0.0], [1.0, 1.0, 0.0])
    """
    p = len(pair_cues)
    src = np.asarray(pair_cues, np.float64)[:, _SOURCE_COLS] if p else np.zeros((0, len(CONTEXT_SOURCES)))
    src = np.where(np.isfinite(src), src, 0.0)
    keys = _cell_keys(ijk) if p else np.zeros(0, np.int64)
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    mx = np.full(src.shape, -np.inf)
    total = np.zeros(src.shape)
    count = np.zeros(p)
    for off in _OFFSETS:
        if not p:
            break
        want = _cell_keys(np.asarray(ijk, np.int64) + off)
        pos = np.minimum(np.searchsorted(sorted_keys, want), p - 1)
        hit = sorted_keys[pos] == want
        nb = order[pos[hit]]
        mx[hit] = np.maximum(mx[hit], src[nb])
        total[hit] += src[nb]
        count[hit] += 1
    mx[count == 0] = 0.0
    mean = total / np.maximum(count, 1)[:, None]
    return np.concatenate([mx, mean, count[:, None]], axis=1).astype(np.float32)


def with_context(pair_cues: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """(P, N_CUES) float32: the pair cues (P, N_PAIR_CUES) of one tile's pairs followed by their context cues."""
    pc = np.asarray(pair_cues, np.float32)[:, :len(PAIR_CUE_NAMES)]
    return np.concatenate([pc, context_cues(pc, ijk)], axis=1)
