"""Rows grouped by patch cell: one stable sort by patch key, shared by ingest (sorted staging runs) and
partition (sorted tile tables).

    >>> import numpy as np
    >>> part = partition_cells(np.array([[1, 0, 0], [0, 0, 0], [1, 0, 0]]))
    >>> part.order.tolist(), part.counts.tolist()
    ([1, 0, 2], [1, 2])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from storage.grid import PatchGrid


@dataclass(frozen=True)
class Partition:
    """Rows grouped by patch.

    Attributes:
        order: (n,) int64 permutation; ``rows[order]`` sorts rows by patch key, stable (rows of one patch
            keep their input order).
        keys: (u,) int64 unique packed patch keys, ascending.
        starts, stops: (u,) int64; the sorted rows ``starts[p]:stops[p]`` lie in patch ``keys[p]``.
            The ranges are non-empty and tile ``0:n`` in order.
    """

    order: np.ndarray
    keys: np.ndarray
    starts: np.ndarray
    stops: np.ndarray

    @property
    def n_rows(self) -> int:
        return len(self.order)

    @property
    def counts(self) -> np.ndarray:
        """(u,) int64 rows per patch."""
        return self.stops - self.starts

    @property
    def ijk(self) -> np.ndarray:
        """(u, 3) int64 patch cells of ``keys``."""
        return PatchGrid.unpack(self.keys)

    def sorted_keys(self) -> np.ndarray:
        """(n,) int64 patch key of each sorted row."""
        return np.repeat(self.keys, self.counts)

    def __repr__(self) -> str:
        return f"Partition(n_rows={self.n_rows}, n_patches={len(self.keys)})"


def empty_partition() -> Partition:
    e = np.zeros(0, dtype=np.int64)
    return Partition(order=e, keys=e.copy(), starts=e.copy(), stops=e.copy())


def partition_cells(ijk: np.ndarray) -> Partition:
    """Group rows by their patch cell.

    Args:
        ijk: (n, 3) int patch index of each row.
    Returns:
        :class:`Partition` (stable order, ascending keys).

    The sort key is the row's cell rank inside the bounding box of the cells (same order as the packed
    key), shifted left with the row number in the low bits: one in-place ``np.sort`` of int64 (SIMD on
    x86) then yields a stable argsort. Measured on 5 M shuffled points: 0.15 s, against 0.51 s for
    ``np.argsort`` (quicksort, unstable) and 1.27 s for ``np.argsort(kind="stable")`` of the packed keys.
    When the rank and the row number do not fit 63 bits together, it falls back to the stable argsort.
    """
    ijk = np.asarray(ijk)
    n = len(ijk)
    if n == 0:
        return empty_partition()
    # per-column reductions: ~20x faster than ijk.min(axis=0) on a C-ordered (n, 3) array
    lo = np.array([ijk[:, a].min() for a in range(3)], dtype=np.int64)
    ext = np.array([ijk[:, a].max() for a in range(3)], dtype=np.int64) - lo + 1
    row_bits = max(1, (n - 1).bit_length())
    cell_bits = max(1, (int(ext[0]) * int(ext[1]) * int(ext[2]) - 1).bit_length())
    if row_bits + cell_bits <= 63:
        rank = ijk[:, 0] - lo[0]  # int64 from here on (lo is int64)
        rank *= ext[1]
        rank += ijk[:, 1]
        rank -= lo[1]
        rank *= ext[2]
        rank += ijk[:, 2]
        rank -= lo[2]
        rank <<= row_bits
        rank |= np.arange(n, dtype=np.int64)
        rank.sort()
        order = rank & ((1 << row_bits) - 1)
        rank >>= row_bits
        sorted_rank = rank
    else:
        packed = PatchGrid.pack(ijk)
        order = np.argsort(packed, kind="stable").astype(np.int64, copy=False)
        sorted_rank = packed[order]
    change = np.flatnonzero(sorted_rank[1:] != sorted_rank[:-1]) + 1
    starts = np.concatenate(([0], change)).astype(np.int64)
    stops = np.concatenate((change, [n])).astype(np.int64)
    keys = PatchGrid.pack(ijk[order[starts]])
    return Partition(order=order, keys=keys, starts=starts, stops=stops)


__all__ = ["Partition", "empty_partition", "partition_cells"]
