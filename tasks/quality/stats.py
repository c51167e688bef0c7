"""The mergeable sums behind the quality figures, and the reports made from them. Pure.

Every distance is accumulated as area-weighted sums plus a fine distance histogram, so results of
chunks and tiles merge exactly (sums of areas and counts, never averages of averages). Percentiles come
from the histogram (0.05 mm bins below 0.5 m, 0.1 % relative above): the value reported is the weighted
mean distance of the bin that holds the quantile.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace

import numpy as np

_FINE_STEP, _FINE_MAX, _N_FINE = 5e-5, 0.5, 10_000
_RATIO, _N_COARSE = 1.001, 12_208  # 0.5 m .. 100 km, then one overflow bin
_N_BINS = _N_FINE + _N_COARSE + 1


def _bins(d: np.ndarray) -> np.ndarray:
    """Histogram bin of each distance: (k,) float64 m -> (k,) int64 in [0, _N_BINS)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        coarse = _N_FINE + np.floor(np.log(np.maximum(d, _FINE_MAX) / _FINE_MAX) / math.log(_RATIO))
    b = np.where(d < _FINE_MAX, np.floor(d / _FINE_STEP), coarse)
    return np.minimum(b, _N_BINS - 1).astype(np.int64)


@dataclass
class SideSums:
    """Area-weighted sums of one direction's distances, per group (row 0: all; row 1 + c: class c).

    All fields are sums (or a max), so two SideSums values of disjoint samples merge exactly.
    """

    n: np.ndarray  # (G,) samples
    w: np.ndarray  # (G,) m²
    wd: np.ndarray  # (G,) m³  (sum of area x distance)
    wd2: np.ndarray  # (G,) m⁴
    dmax: np.ndarray  # (G,) m
    within: np.ndarray  # (G, T) m² within each tau
    masked: np.ndarray  # (G,) m² of samples under the face mask
    far: np.ndarray  # (G, 2) m² beyond the hole threshold: all, under the mask
    holes: np.ndarray  # (G, 2) m² not covered along the normal: all, under the mask
    hist_w: np.ndarray  # (G, B) m² per distance bin
    hist_wd: np.ndarray  # (G, B) m³ per distance bin

    @classmethod
    def empty(cls, groups: int, n_taus: int) -> SideSums:
        z = lambda *s: np.zeros(s)
        return cls(np.zeros(groups, np.int64), z(groups), z(groups), z(groups), z(groups), z(groups, n_taus),
                   z(groups), z(groups, 2), z(groups, 2), z(groups, _N_BINS), z(groups, _N_BINS))

    def add(self, d, w, cls, masked, holes, taus, hole_m) -> None:
        """d, w: (k,) float64 m, m²; cls: (k,) int64 class (-1: none); masked, holes: (k,) bool."""
        has = cls >= 0
        g = np.concatenate([np.zeros(len(d), np.int64), 1 + cls[has]])
        d, w, masked, holes = (np.concatenate([x, x[has]]) for x in (d, w, masked, holes))
        G = len(self.n)
        s = lambda x: np.bincount(g, x, minlength=G)
        wd = w * d
        self.n += np.bincount(g, minlength=G)
        self.w += s(w)
        self.wd += s(wd)
        self.wd2 += s(wd * d)
        np.maximum.at(self.dmax, g, d)
        for t, tau in enumerate(taus):
            self.within[:, t] += s(w * (d <= tau))
        self.masked += s(w * masked)
        for i, flag in enumerate((d > hole_m, holes)):
            into = self.far if i == 0 else self.holes
            into[:, 0] += s(w * flag)
            into[:, 1] += s(w * (flag & masked))
        flat = g * _N_BINS + _bins(d)
        self.hist_w += np.bincount(flat, w, minlength=G * _N_BINS).reshape(G, _N_BINS)
        self.hist_wd += np.bincount(flat, wd, minlength=G * _N_BINS).reshape(G, _N_BINS)

    def __add__(self, other: SideSums) -> SideSums:
        return SideSums(**{k: (np.maximum if k == "dmax" else np.add)(v, getattr(other, k))
                        for k, v in vars(self).items()})

    def quantile(self, g: int, q: float) -> float:
        cum = np.cumsum(self.hist_w[g])
        if cum[-1] <= 0:
            return math.nan
        k = min(int(np.searchsorted(cum, q * cum[-1])), _N_BINS - 1)
        return float(self.hist_wd[g, k] / self.hist_w[g, k])

    def stats(self, g: int) -> DistanceStats:
        w = self.w[g]
        div = (lambda x: float(x / w)) if w > 0 else (lambda x: math.nan)
        return DistanceStats(
            n_samples=int(self.n[g]), area_m2=float(w), mean_m=div(self.wd[g]),
            median_m=self.quantile(g, 0.5), p90_m=self.quantile(g, 0.9), p95_m=self.quantile(g, 0.95),
            rms_m=math.sqrt(div(self.wd2[g])), max_m=float(self.dmax[g]) if w > 0 else math.nan,
            within=tuple(div(x) for x in self.within[g]),
        )


@dataclass(frozen=True)
class DistanceStats:
    """Area-weighted statistics of one direction's distances (metres); within[i]: area fraction <= taus[i]."""

    n_samples: int
    area_m2: float
    mean_m: float
    median_m: float
    p90_m: float
    p95_m: float
    rms_m: float
    max_m: float
    within: tuple[float, ...]


def _fscore(p: float, r: float) -> float:
    if math.isnan(p) or math.isnan(r):
        return math.nan
    return 0.0 if p + r == 0 else 2 * p * r / (p + r)


def _jsonable(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, (tuple, list)):
        return [_jsonable(v) for v in x]
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    return x


@dataclass(frozen=True)
class QualityReport:
    """Measured quality of a predicted mesh against the truth (metres, m², fractions in [0, 1]).

    accuracy: pred -> truth; completeness: truth -> pred. chamfer_m: mean of the two mean distances;
    chamfer_l2_m2: mean of the two mean squared distances. precision/recall/fscore: one per tau.
    uncovered_*: holes, the truth area under the face mask where no predicted surface crosses the
    segment +- hole_threshold_m along the truth normal; far_*: the truth area under the mask farther
    than hole_threshold_m from the prediction (this one shrinks a hole by the threshold all round).
    evaluated_area_m2: the truth area under the mask (in per_class entries: all of the class's area).
    per_class: keyed by class name; pred samples count towards the class of their nearest truth face.
    """

    taus_m: tuple[float, ...]
    accuracy: DistanceStats
    completeness: DistanceStats
    chamfer_m: float
    chamfer_l2_m2: float
    precision: tuple[float, ...]
    recall: tuple[float, ...]
    fscore: tuple[float, ...]
    hole_threshold_m: float
    evaluated_area_m2: float
    uncovered_area_m2: float
    uncovered_fraction: float
    far_area_m2: float
    far_fraction: float
    spacing_m: float
    max_distance_m: float | None = None
    per_class: Mapping[str, QualityReport] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-friendly: plain floats, lists and dicts; NaN and infinity become None."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        out |= {"accuracy": vars(self.accuracy), "completeness": vars(self.completeness),
                "per_class": {k: v.to_dict() for k, v in self.per_class.items()}}
        return _jsonable(out)

    def __str__(self) -> str:
        f = lambda x: f"{x:8.4f}" if math.isfinite(x) else f"{x!s:>8}"
        rows = [f"{'':14}{'mean':>8}{'median':>8}{'p90':>8}{'p95':>8}{'RMS':>8}{'max':>8}  [m]  area m²"]
        for name, s in (("accuracy", self.accuracy), ("completeness", self.completeness)):
            cells = "".join(f(x) for x in (s.mean_m, s.median_m, s.p90_m, s.p95_m, s.rms_m, s.max_m))
            rows.append(f"{name:14}{cells}  {s.area_m2:12.2f}")
        rows.append(f"chamfer {self.chamfer_m:.4f} m, L2 {self.chamfer_l2_m2:.6f} m², "
                    f"spacing {self.spacing_m} m")
        rows.append(f"{'tau m':>8}{'precision':>10}{'recall':>8}{'F':>8}")
        rows += [f"{t:8.3f}{p:10.3f}{r:8.3f}{fs:8.3f}"
                 for t, p, r, fs in zip(self.taus_m, self.precision, self.recall, self.fscore)]
        rows.append(f"uncovered (no surface within +-{self.hole_threshold_m} m along the normal): "
                    f"{self.uncovered_area_m2:.2f} m² of {self.evaluated_area_m2:.2f} m² "
                    f"({100 * self.uncovered_fraction:.1f} %); farther than that: {self.far_area_m2:.2f} m²")
        if self.per_class:
            head = f"{'class':14}{'acc':>8}{'comp':>8}{'F@' + str(self.taus_m[0]):>8}"
            rows.append(f"{head}{'area m²':>12}{'holes m²':>10}")
            for name, r in self.per_class.items():
                rows.append(f"{name:14}{f(r.accuracy.mean_m)}{f(r.completeness.mean_m)}{f(r.fscore[0])}"
                            f"{r.completeness.area_m2:12.2f}{r.uncovered_area_m2:10.2f}")
        return "\n".join(rows)


@dataclass(frozen=True)
class QualityPartial:
    """Mergeable sums behind a QualityReport (one chunk, tile or region): ``(a + b).report()``."""

    accuracy: SideSums
    completeness: SideSums
    taus_m: tuple[float, ...]
    hole_threshold_m: float
    spacing_m: float
    max_distance_m: float | None
    class_names: tuple[str, ...]

    def __add__(self, other: QualityPartial) -> QualityPartial:
        key = lambda q: (q.taus_m, q.hole_threshold_m, q.class_names)
        if key(self) != key(other):
            raise ValueError("cannot merge partials measured with different taus, thresholds or classes")
        return replace(self, accuracy=self.accuracy + other.accuracy,
                       completeness=self.completeness + other.completeness)

    def report(self) -> QualityReport:
        per_class = {}
        for c, name in enumerate(self.class_names):
            if self.accuracy.n[1 + c] or self.completeness.n[1 + c]:
                per_class[name] = self._report(1 + c, {}, masked=False)
        return self._report(0, per_class, masked=True)

    def _report(self, g: int, per_class: dict, masked: bool) -> QualityReport:
        acc, comp, side = self.accuracy.stats(g), self.completeness.stats(g), self.completeness
        m = int(masked)
        area, holes, far = side.masked[g] if masked else side.w[g], side.holes[g, m], side.far[g, m]
        frac = (lambda x: float(x / area)) if area > 0 else (lambda x: math.nan)
        return QualityReport(
            taus_m=self.taus_m, accuracy=acc, completeness=comp,
            chamfer_m=0.5 * (acc.mean_m + comp.mean_m), chamfer_l2_m2=0.5 * (acc.rms_m**2 + comp.rms_m**2),
            precision=acc.within, recall=comp.within,
            fscore=tuple(_fscore(p, r) for p, r in zip(acc.within, comp.within)),
            hole_threshold_m=self.hole_threshold_m, evaluated_area_m2=float(area),
            uncovered_area_m2=float(holes), uncovered_fraction=frac(holes),
            far_area_m2=float(far), far_fraction=frac(far),
            spacing_m=self.spacing_m, max_distance_m=self.max_distance_m, per_class=per_class,
        )

