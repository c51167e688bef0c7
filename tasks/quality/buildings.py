"""Accuracy without truth per building: the held-out MLS strips' distance histograms (:class:`HeldOutSums`) of
each building (:mod:`tasks.geometry.footprints`), mergeable across tiles, and the building rows of
``report/holdout.json``. Pure.

A building spans tiles, so its sums are added up tile by tile, like the campus's. A dense histogram is
``N_BINS`` counts (80 kB); kept per building and model that would grow with the city, so the sums are sparse:
only the (building, bin) pairs that hold a point, never more than the held-out points.

    >>> import numpy as np
    >>> a = GroupedSums.of(np.array([1, 1, 0]), np.array([0.01, 0.03, 0.5]))  # two points on building 1
    >>> b = GroupedSums.of(np.array([1, 2]), np.array([0.02, 0.2]))  # the next tile
    >>> s = GroupedSums.merge([a, b])
    >>> s.groups().tolist(), s.sums(1).figures()["points"], s.sums(1).figures()["median_m"]
    ([0, 1, 2], 3, 0.02005)
    >>> s.sums(7).n
    0
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.quality.heldout import N_BINS, HeldOutSums


@dataclass(frozen=True, eq=False)
class GroupedSums:
    """Held-out distance histograms of many groups (building ids; 0: no building), sparse: keys (k,) int64
    ``group * N_BINS + bin``, sorted and unique, and their counts (k,) int64 (> 0)."""

    keys: np.ndarray
    counts: np.ndarray

    @classmethod
    def empty(cls) -> GroupedSums:
        return cls(np.zeros(0, np.int64), np.zeros(0, np.int64))

    @classmethod
    def of(cls, groups: np.ndarray, distances_m: np.ndarray) -> GroupedSums:
        """The sums of (k,) float64 distances (metres; inf: no surface near) in (k,) int groups (>= 0)."""
        g = np.asarray(groups, np.int64)
        order = np.argsort(g, kind="stable")
        gs, d = g[order], np.asarray(distances_m, np.float64)[order]
        starts = np.flatnonzero(np.r_[True, gs[1:] != gs[:-1]]) if len(gs) else np.zeros(0, np.int64)
        keys, counts = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
        for a, b in zip(starts, np.r_[starts[1:], len(gs)]):  # one pass per group, not per point
            c = HeldOutSums.of(d[a:b]).counts
            nz = np.flatnonzero(c)
            keys.append(gs[a] * N_BINS + nz)
            counts.append(c[nz])
        return cls(np.concatenate(keys), np.concatenate(counts))

    @classmethod
    def merge(cls, parts: list[GroupedSums]) -> GroupedSums:
        """The sums of ``parts`` added up (exactly: counts of the same group and bin are summed)."""
        keys = np.concatenate([p.keys for p in parts] + [np.zeros(0, np.int64)])
        counts = np.concatenate([p.counts for p in parts] + [np.zeros(0, np.int64)])
        u, inv = np.unique(keys, return_inverse=True)
        total = np.zeros(len(u), np.int64)
        np.add.at(total, inv, counts)
        return cls(u, total)

    def __add__(self, other: GroupedSums) -> GroupedSums:
        return GroupedSums.merge([self, other])

    def groups(self) -> np.ndarray:
        """(g,) int64 the groups that hold a point, ascending."""
        return np.unique(self.keys // N_BINS)

    def sums(self, group: int) -> HeldOutSums:
        """The dense :class:`HeldOutSums` of one group (empty where it holds no point)."""
        a, b = np.searchsorted(self.keys, [group * N_BINS, (group + 1) * N_BINS])
        counts = np.zeros(N_BINS, np.int64)
        counts[self.keys[a:b] - group * N_BINS] = self.counts[a:b]
        return HeldOutSums(counts)


def building_rows(footprints, by_model: dict[str, GroupedSums], origin: np.ndarray) -> list[dict]:
    """The buildings of ``footprints`` (a :class:`tasks.geometry.footprints.Footprints`) that hold held-out
    points, by id, then "other" (id 0: points on no building: ground, trees, cars), each {"id", "area_m2",
    "height_m", "centroid": [x, y] campus-local metres, "centroid_world": [x, y] + ``origin`` (3,) float64 world
    metres, "models": {model: HeldOutSums.figures()}} ("other": {"id": 0, "name": "other", "models"})."""
    ids = sorted({int(g) for s in by_model.values() for g in s.groups()})
    rows = []
    for b in [i for i in ids if i > 0] + [0] * (0 in ids):
        models = {m: s.sums(b).figures() for m, s in by_model.items()}
        if b == 0:
            rows.append({"id": 0, "name": "other", "models": models})
            continue
        x, y = (float(v) for v in footprints.centroid_xy[b - 1])
        rows.append({"id": b, "area_m2": round(float(footprints.area_m2[b - 1]), 1),
                     "height_m": round(float(footprints.height_m[b - 1]), 2), "centroid": [round(x, 2), round(y, 2)],
                     "centroid_world": [round(x + float(origin[0]), 2), round(y + float(origin[1]), 2)],
                     "models": models})
    return rows


__all__ = ["GroupedSums", "building_rows"]
