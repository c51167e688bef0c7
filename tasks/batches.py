"""Batching units into task runs: a Prefect task run costs ~0.3 s here, so a thousand small units must
not become a thousand task runs. Pure; used by the stage packages that decide how their units are mapped."""

from __future__ import annotations


def balanced_batches(items: list, weights: list[float], n_batches: int) -> list[list]:
    """Split items into at most ``n_batches`` batches of about equal total weight (largest first,
    greedy), each batch in input order.

    >>> balanced_batches(["a", "b", "c", "d"], [4.0, 1.0, 1.0, 2.0], 2)
    [['a'], ['b', 'c', 'd']]
    """
    n = max(1, min(n_batches, len(items)))
    order = sorted(range(len(items)), key=lambda i: -weights[i])
    loads, members = [0.0] * n, [[] for _ in range(n)]
    for i in order:
        b = loads.index(min(loads))
        loads[b] += weights[i]
        members[b].append(i)
    return [[items[i] for i in sorted(m)] for m in members if m]


def fixed_batches(items: list, size: int) -> list[list]:
    """Consecutive batches of ``size`` items (the last may be shorter).

    >>> fixed_batches([1, 2, 3], 2)
    [[1, 2], [3]]
    """
    return [items[i:i + size] for i in range(0, len(items), max(1, size))]
