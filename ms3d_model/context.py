"""Neighbourhood cues: a pair's cues seen next to its neighbours' in the same tile.

A defect (a hole, a misaligned storey, a recess) covers several patch cells, and the cells at its rim carry
weak evidence of their own. What their neighbours show is the strongest extra cue the trees found (+0.025
validation AP on the demo campuses). The neighbourhood is the 26 cells around a pair's cell that hold a pair
of the **same tile**: classify grades a tile at a time, and training builds its pairs per tile the same way,
so the cue means the same in both. Cells at a tile's border see fewer neighbours (``nb_count`` says so).
"""

from __future__ import annotations

import numpy as np

from .cues import (  # noqa: F401 - the doctests use some
    CONTEXT_CUE_NAMES,
    CONTEXT_SOURCES,
    CUE_NAMES,
    OWN_CUE_NAMES,
    PAIR_CUE_NAMES,
    RELATIVE_SOURCES,
    SURFACE_CONTEXT_SOURCES,
    SURFACE_CUE_NAMES,
)

_SOURCE_COLS = np.array([PAIR_CUE_NAMES.index(n) for n in CONTEXT_SOURCES])
_SURFACE_SOURCE_COLS = np.array([OWN_CUE_NAMES.index(n) for n in SURFACE_CONTEXT_SOURCES])
_RELATIVE_SOURCE_COLS = np.array([OWN_CUE_NAMES.index(n) for n in RELATIVE_SOURCES])
# the columns of CUE_NAMES that describe a pair's neighbours, not the pair (clean-context copies swap them); the
# "around_" / "vs_around_" columns stay with their pair (a copy keeps its own offset against its own neighbours)
CONTEXT_COLUMNS = np.array([i for i, n in enumerate(CUE_NAMES) if n.startswith("nb_")])
_OFFSETS = np.array([(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) != (0, 0, 0)])


def _cell_keys(ijk: np.ndarray) -> np.ndarray:
    """(P,) int64 keys of (P, 3) cells, unique for |i|, |j|, |k| < 2**20."""
    o = (np.asarray(ijk, np.int64) + (1 << 20)) & ((1 << 21) - 1)
    return (o[:, 0] << 42) | (o[:, 1] << 21) | o[:, 2]


def context_cues(pair_cues: np.ndarray, ijk: np.ndarray, columns: np.ndarray = _SOURCE_COLS,
                 with_count: bool = True) -> np.ndarray:
    """(P, len(CONTEXT_CUE_NAMES)) float32: per pair, the max and the mean of the :data:`CONTEXT_SOURCES` cues
    over the pairs in its 26 neighbouring cells, then their count. 0 where a pair has no neighbour.

    pair_cues: (P, >= N_PAIR_CUES) float cues of the pairs of one tile (:data:`PAIR_CUE_NAMES` order);
    ijk: (P, 3) int patch cells of the pairs (one pair per cell); columns: the source columns of
    ``pair_cues`` (default: the :data:`CONTEXT_SOURCES`); with_count: append the neighbour count.

    >>> cues = np.zeros((3, len(PAIR_CUE_NAMES))); cues[:, PAIR_CUE_NAMES.index("p2m_p90")] = [0.1, 0.5, 9.0]
    >>> c = dict(zip(CONTEXT_CUE_NAMES, context_cues(cues, np.array([[0, 0, 0], [1, 1, 0], [5, 0, 0]])).T))
    >>> c["nb_max_p2m_p90"].tolist(), c["nb_count"].tolist()
    ([0.5, 0.10000000149011612, 0.0], [1.0, 1.0, 0.0])
    """
    p = len(pair_cues)
    src = np.asarray(pair_cues, np.float64)[:, columns] if p else np.zeros((0, len(columns)))
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
    parts = [mx, mean] + ([count[:, None]] if with_count else [])
    return np.concatenate(parts, axis=1).astype(np.float32)


def with_context(own_cues: np.ndarray, ijk: np.ndarray) -> np.ndarray:
    """(P, N_CUES) float32 in :data:`CUE_NAMES` order: the own cues (P, len(OWN_CUE_NAMES)) of one tile's pairs
    (:func:`~ms3d_model.cues.batch_cues`) with their context cues put in their places."""
    own = np.asarray(own_cues, np.float32)
    if own.shape[1] != len(OWN_CUE_NAMES):
        raise ValueError(f"expected {len(OWN_CUE_NAMES)} own cue columns, got {own.shape[1]}")
    n_pair, n_rel = len(PAIR_CUE_NAMES), len(RELATIVE_SOURCES)
    around = context_cues(own, ijk, _RELATIVE_SOURCE_COLS, with_count=False)[:, n_rel:]  # the neighbours' means
    return np.concatenate([own[:, :n_pair], context_cues(own, ijk), own[:, n_pair:],
                           context_cues(own, ijk, _SURFACE_SOURCE_COLS, with_count=False), around,
                           own[:, _RELATIVE_SOURCE_COLS] - around], axis=1)


def clean_context_copies(cues: np.ndarray, labels: np.ndarray, share: float, seed: int = 0,
                         clean_below: float = 0.15) -> tuple[np.ndarray, np.ndarray]:
    """Training pairs plus copies of a ``share`` of them whose context cues come from a good pair in a clean
    neighbourhood (two or more neighbours, none with more than ``clean_below`` of its points 15 cm off).

    Synth defects span several cells, so trees trained on them learn "a clean neighbourhood means good" and
    miss a defect of one cell in a good wall (a single recessed window): measured, a 0.3 m offset cell
    between two good cells scored 0.1-0.2 against 0.8 for trees without context. The copies teach that
    a pair's own evidence can say bad whatever its neighbours say (validation AP on bad 0.9053 -> 0.9115 at
    share 0.25, demo seeds 7 + 11). cues: (B, N_CUES) float32; labels: (B,). Returns the (B + c, N_CUES)
    cues and (B + c,) labels; unchanged when share <= 0 or no donor exists.
    """
    cues, labels = np.asarray(cues), np.asarray(labels)
    if share <= 0 or cues.shape[1] < len(CUE_NAMES) or not len(cues):
        return cues, labels
    count = cues[:, CUE_NAMES.index("nb_count")]
    dirty = cues[:, CUE_NAMES.index("nb_max_p2m_frac_15cm")]
    donors = np.flatnonzero((labels == 0) & (count >= 2) & (dirty < clean_below))
    if not len(donors):
        return cues, labels
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(cues), int(round(share * len(cues))), replace=False)
    copies = cues[pick].copy()
    copies[:, CONTEXT_COLUMNS] = cues[rng.choice(donors, len(pick))][:, CONTEXT_COLUMNS]
    return np.concatenate([cues, copies]), np.concatenate([labels, labels[pick]])
