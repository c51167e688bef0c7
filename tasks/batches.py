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


def hilbert_index(i: int, j: int, bits: int = 26) -> int:
    """Position of cell (i, j) (non-negative ints below 2**bits) along the Hilbert curve of that grid: any
    run of consecutive positions is a connected, compact set of cells (the Z-order jumps across the grid).

    >>> [hilbert_index(i, j, 1) for i, j in ((0, 0), (0, 1), (1, 1), (1, 0))]
    [0, 1, 2, 3]
    >>> sorted(hilbert_index(i, j, 2) for i in range(4) for j in range(4)) == list(range(16))
    True
    """
    n = 1 << bits
    d = 0
    s = n >> 1
    while s:
        rx, ry = int(i & s > 0), int(j & s > 0)
        d += s * s * ((3 * rx) ^ ry)
        if ry == 0:  # rotate the quadrant so that the curve's pieces join
            if rx == 1:
                i, j = n - 1 - i, n - 1 - j
            i, j = j, i
        s >>= 1
    return d


def contiguous_batches(items: list, weights: list[float], n_batches: int) -> list[list]:
    """Split ``items`` (already in spatial order) into at most ``n_batches`` runs of consecutive items of
    about equal total weight: each batch is a compact stretch of the order, not items scattered over the
    campus. A run is closed when the next item would carry it past its share; the batches heaviest first.

    >>> contiguous_batches(["a", "b", "c", "d"], [1.0, 1.0, 1.0, 1.0], 2)
    [['a', 'b'], ['c', 'd']]
    >>> contiguous_batches(["a", "b", "c", "d"], [5.0, 1.0, 1.0, 1.0], 2)
    [['a'], ['b', 'c', 'd']]
    >>> contiguous_batches([], [], 3)
    []
    """
    if not items:
        return []
    n = max(1, min(n_batches, len(items)))
    total = float(sum(weights)) or 1.0
    out, loads, cur, acc = [], [], [], 0.0
    for k, (it, w) in enumerate(zip(items, weights)):
        left = len(items) - k  # items not yet placed, this one included
        share = total * (len(out) + 1) / n  # the running total this batch should end at
        if cur and (acc + w / 2 > share or left <= n - len(out) - 1) and len(out) < n - 1:
            out.append(cur)
            loads.append(acc - sum(loads))
            cur = []
        cur.append(it)
        acc += w
    out.append(cur)
    loads.append(acc - sum(loads))
    order = sorted(range(len(out)), key=lambda b: -loads[b])  # stable: ties keep the spatial order
    return [out[b] for b in order]
