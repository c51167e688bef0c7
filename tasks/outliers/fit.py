"""Patch outlier removal by face/point counts (Liu et al. 2023, §3.2.2).

The paper histograms the number of faces (or points) per patch, fits a normal curve, and drops the
patches in the thin tails: nearly empty slivers and overfull clutter are not representative pairs.

Counts per patch are right-skewed (a patch cut by a facade holds a few faces, one full of vegetation
thousands), so the normal is fitted to ``log10(count)`` by default. The fit is robust (median and
1.4826 x MAD, which equal mean and sigma for a normal sample) so that the outliers being looked for do not
widen the band that is supposed to catch them; ``method="moments"`` uses the plain mean/std instead.

Patches with a zero count are neither fitted nor flagged here: a pair missing one side (no MLS points
behind a roof, no mesh over a hole) is a different condition, handled where pairs are formed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path

MAD_TO_SIGMA = 1.482602218505602  # 1 / Phi^-1(3/4)


@dataclass(frozen=True)
class OutlierFit:
    """A normal fit to patch counts and the band outside which patches are outliers.

    mean, std: of the fitted normal, in log10(count) units when ``log`` else in count units.
    low, high: band limits in count units (a patch is kept when low <= count <= high).
    mask: (n,) bool, True for flagged patches (always False where count == 0).
    n_flagged: mask.sum(); n_fitted: patches with count > 0.
    """

    mean: float
    std: float
    low: float
    high: float
    log: bool
    mask: np.ndarray = field(repr=False)
    n_flagged: int
    n_fitted: int

    def __repr__(self) -> str:
        unit = "log10(count)" if self.log else "count"
        return (f"OutlierFit({unit} mean={self.mean:.3f} std={self.std:.3f}, keep counts in "
                f"[{self.low:.1f}, {self.high:.1f}], flagged {self.n_flagged}/{self.n_fitted})")


def fit_count_outliers(counts: np.ndarray, sigma_low: float, sigma_high: float, log: bool = True,
                       method: str = "robust") -> OutlierFit:
    """Fit a normal to per-patch counts and flag the tails.

    Args:
        counts: (n,) int faces or points per patch.
        sigma_low, sigma_high: band half-widths in standard deviations below / above the mean
            (config ``outlier_sigma_low`` = 2, ``outlier_sigma_high`` = 3).
        log: fit log10(count) (default) rather than count.
        method: "robust" (median, 1.4826 x MAD) or "moments" (mean, std).
    Returns:
        :class:`OutlierFit`. With fewer than 3 non-zero counts or zero spread nothing is flagged.

    Example: counts [10, 12, 9, 11, 10, 500] flag only the 500.
    """
    counts = np.asarray(counts).reshape(-1)
    if counts.size and counts.min() < 0:
        raise ValueError("counts must be non-negative")
    if method not in ("robust", "moments"):
        raise ValueError(f"method must be 'robust' or 'moments', got {method!r}")
    fitted = counts > 0
    values = counts[fitted].astype(np.float64)
    if log:
        values = np.log10(values)
    mask = np.zeros(len(counts), dtype=bool)
    if len(values) < 3:
        return OutlierFit(np.nan, np.nan, 0.0, np.inf, log, mask, 0, len(values))
    if method == "robust":
        mean = float(np.median(values))
        std = float(MAD_TO_SIGMA * np.median(np.abs(values - mean)))
        if std == 0.0:  # more than half the counts equal: fall back to the moments
            std = float(values.std())
    else:
        mean, std = float(values.mean()), float(values.std())
    if std == 0.0:
        return OutlierFit(mean, 0.0, 0.0, np.inf, log, mask, 0, len(values))
    lo_v, hi_v = mean - sigma_low * std, mean + sigma_high * std
    mask[fitted] = (values < lo_v) | (values > hi_v)
    low, high = (10.0 ** lo_v, 10.0 ** hi_v) if log else (lo_v, hi_v)
    return OutlierFit(mean, std, float(low), float(high), log, mask, int(mask.sum()), len(values))


def flag_patch_count_outliers(n_points: np.ndarray, n_faces: np.ndarray, sigma_low: float, sigma_high: float,
                              log: bool = True):
    """Flag outlier patches on both sides of the pairs.

    n_points, n_faces: (u,) int per patch (the patches table columns).
    Returns (points_fit, faces_fit, outlier (u,) bool = either side flagged).
    """
    pf = fit_count_outliers(n_points, sigma_low, sigma_high, log)
    ff = fit_count_outliers(n_faces, sigma_low, sigma_high, log)
    return pf, ff, pf.mask | ff.mask


def save_histogram_png(counts: np.ndarray, fit: OutlierFit, path: str | Path, title: str) -> Path:
    """Histogram of the fitted counts with the normal curve and the kept band, as a PNG (atomic write).

    counts: (n,) int, the array given to :func:`fit_count_outliers`. Uses matplotlib's Agg canvas directly
    (no pyplot state), so it is safe in worker threads.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    counts = np.asarray(counts).reshape(-1)
    values = counts[counts > 0].astype(np.float64)
    if fit.log:
        values = np.log10(values)
    fig = Figure(figsize=(7, 4), dpi=100)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    if len(values):
        n_bins = int(np.clip(np.sqrt(len(values)), 10, 80))
        _, edges, _ = ax.hist(values, bins=n_bins, color="0.6", label=f"{len(values)} patches")
        if np.isfinite(fit.std) and fit.std > 0:
            lo_v = np.log10(fit.low) if fit.log else fit.low
            hi_v = np.log10(fit.high) if fit.log else fit.high
            ax.axvspan(lo_v, hi_v, color="tab:green", alpha=0.12, label="kept band")
            xs = np.linspace(min(edges[0], lo_v), max(edges[-1], hi_v), 400)
            scale = len(values) * (edges[1] - edges[0])
            pdf = np.exp(-0.5 * ((xs - fit.mean) / fit.std) ** 2) / (fit.std * np.sqrt(2 * np.pi))
            ax.plot(xs, scale * pdf, color="tab:blue", label=f"normal fit (mean {fit.mean:.2f}, sd {fit.std:.2f})")
            for v in (lo_v, hi_v):
                ax.axvline(v, color="tab:red", lw=1)
        ax.legend(loc="upper right", fontsize=8, title=f"flagged {fit.n_flagged}", title_fontsize=8)
    else:
        ax.text(0.5, 0.5, "no non-empty patches", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel("log10(count per patch)" if fit.log else "count per patch")
    ax.set_ylabel("patches")
    ax.set_title(title)
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
