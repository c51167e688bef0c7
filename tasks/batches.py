"""Batching units into task runs: a Prefect task run costs ~0.3 s here, so a thousand small units must
not become a thousand task runs. Pure; used by the stage packages that decide how their units are mapped."""

from __future__ import annotations


def balanced_batches(items: list, weights: list[float], n_batches: int) -> list[list]:
    """Split items into at most ``n_batches`` batches of about equal total weight (largest first,
    greedy), each batch in input order; the batches heaviest first (a scheduler that starts them in
    order then ends with the light ones: longest-processing-time order).

    >>> balanced_batches(["a", "b", "c", "d"], [4.0, 1.0, 1.0, 2.0], 2)
    [['a'], ['b', 'c', 'd']]
    >>> balanced_batches(["a", "b", "c"], [1.0, 5.0, 3.0], 3)
    [['b'], ['c'], ['a']]
    """
    n = max(1, min(n_batches, len(items)))
    order = sorted(range(len(items)), key=lambda i: -weights[i])
    loads, members = [0.0] * n, [[] for _ in range(n)]
    for i in order:
        b = loads.index(min(loads))
        loads[b] += weights[i]
        members[b].append(i)
    by_load = sorted((b for b in range(n) if members[b]), key=lambda b: -loads[b])  # stable: ties keep order
    return [[items[i] for i in sorted(members[b])] for b in by_load]


def fixed_batches(items: list, size: int) -> list[list]:
    """Consecutive batches of ``size`` items (the last may be shorter).

    >>> fixed_batches([1, 2, 3], 2)
    [[1, 2], [3]]
    """
    return [items[i:i + size] for i in range(0, len(items), max(1, size))]
