"""Accuracy without truth: distances of the held-out MLS strips (:mod:`tasks.geometry.holdout`) to a model, as
mergeable sums (one histogram per tile, added up for the campus). Pure.

The held-out points shaped neither the input mesh nor the repair, so their distance to a model is an
independent measure of it: median, 90th percentile, share within 5 and 10 cm. Distances are binned every
``BIN_M`` (0.1 mm) up to ``CAP_M``; a point farther (or without a surface within the cap) counts in the last
bin, so the shares are exact and the percentiles good to a bin.

    >>> import numpy as np
    >>> s = HeldOutSums.of(np.array([0.01, 0.02, 0.03, 0.2, 5.0]))
    >>> f = (s + HeldOutSums.of(np.array([0.04]))).figures()
    >>> f["points"], round(f["median_m"], 4), f["within_5cm"], f["within_10cm"]
    (6, 0.0301, 0.667, 0.667)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BIN_M = 1e-4
CAP_M = 1.0
N_BINS = int(round(CAP_M / BIN_M)) + 1  # the last bin: CAP_M and beyond


@dataclass(frozen=True, eq=False)
class HeldOutSums:
    """counts: (N_BINS,) int64 held-out points per distance bin (the last: >= CAP_M or no surface)."""

    counts: np.ndarray

    @classmethod
    def empty(cls) -> HeldOutSums:
        return cls(np.zeros(N_BINS, np.int64))

    @classmethod
    def of(cls, distances_m: np.ndarray) -> HeldOutSums:
        """The sums of (k,) float64 unsigned distances (metres; inf: no surface near)."""
        d = np.asarray(distances_m, np.float64)
        b = np.minimum(np.floor(np.where(np.isfinite(d), d, CAP_M) / BIN_M), N_BINS - 1).astype(np.int64)
        return cls(np.bincount(b, minlength=N_BINS).astype(np.int64))

    def __add__(self, other: HeldOutSums) -> HeldOutSums:
        return HeldOutSums(self.counts + other.counts)

    @property
    def n(self) -> int:
        return int(self.counts.sum())

    def percentile_m(self, q: float) -> float | None:
        """The q-quantile (0..1) as its bin's centre (metres); None without points; CAP_M when beyond it."""
        if not self.n:
            return None
        b = int(np.searchsorted(np.cumsum(self.counts), q * self.n))
        return CAP_M if b >= N_BINS - 1 else round((b + 0.5) * BIN_M, 6)

    def within(self, tau_m: float) -> float | None:
        """Share of the points closer than ``tau_m`` (a multiple of BIN_M below CAP_M)."""
        return round(float(self.counts[:int(round(tau_m / BIN_M))].sum()) / self.n, 3) if self.n else None

    def figures(self) -> dict:
        """{"points", "median_m", "p90_m", "within_5cm", "within_10cm"} (None figures without points)."""
        return {"points": self.n, "median_m": self.percentile_m(0.5), "p90_m": self.percentile_m(0.9),
                "within_5cm": self.within(0.05), "within_10cm": self.within(0.10)}


def faces_near(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray, pad_m: float) -> np.ndarray:
    """(m,) bool: triangles ((m, 3, 3) float) whose bounding box meets the box [lo - pad, hi + pad]."""
    if len(tri) == 0:
        return np.zeros(0, bool)
    tmin, tmax = tri.min(axis=1), tri.max(axis=1)
    return np.all((tmax >= np.asarray(lo) - pad_m) & (tmin <= np.asarray(hi) + pad_m), axis=1)


__all__ = ["BIN_M", "CAP_M", "HeldOutSums", "faces_near"]
