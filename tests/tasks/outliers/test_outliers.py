import numpy as np
import pytest

from tasks.outliers.fit import fit_count_outliers, flag_patch_count_outliers, save_histogram_png


def _sample(seed=0, n=4000):
    rng = np.random.default_rng(seed)
    clean = np.maximum(1, np.round(rng.lognormal(mean=np.log(200), sigma=0.5, size=n))).astype(np.int64)
    extremes = np.array([1, 2, 1, 60_000, 100_000, 250_000])
    return clean, extremes


def test_flags_injected_extremes_and_keeps_the_bulk():
    clean, extremes = _sample()
    counts = np.concatenate([clean, extremes, np.zeros(50, np.int64)])
    fit = fit_count_outliers(counts, sigma_low=2.0, sigma_high=3.0)
    n = len(clean)
    assert fit.mask[n:n + len(extremes)].all()  # every injected extreme is flagged
    assert not fit.mask[n + len(extremes):].any()  # zero counts are never flagged
    kept = (clean >= fit.low) & (clean <= fit.high)
    assert kept.mean() >= 0.95
    assert np.array_equal(kept, ~fit.mask[:n])
    assert fit.n_flagged == int(fit.mask.sum()) and fit.n_fitted == n + len(extremes)
    assert abs(fit.mean - np.log10(200)) < 0.02 and abs(fit.std - 0.5 / np.log(10)) < 0.02


def test_small_example_and_degenerate_inputs():
    fit = fit_count_outliers(np.array([10, 12, 9, 11, 10, 500]), 2.0, 3.0)
    assert fit.mask.tolist() == [False] * 5 + [True]
    same = fit_count_outliers(np.full(10, 7), 2.0, 3.0)
    assert same.n_flagged == 0
    tiny = fit_count_outliers(np.array([0, 3]), 2.0, 3.0)
    assert tiny.n_flagged == 0 and tiny.mask.tolist() == [False, False]
    with pytest.raises(ValueError):
        fit_count_outliers(np.array([-1, 2, 3]), 2.0, 3.0)


def test_linear_moments_option():
    counts = np.array([100, 101, 99, 100, 102, 98, 100, 1000])
    fit = fit_count_outliers(counts, 2.0, 2.0, log=False, method="moments")
    assert not fit.log and fit.mask[-1] and fit.high < 1000


def test_flag_both_sides():
    clean, _ = _sample(1, 500)
    n_points = np.concatenate([clean * 10, [0, 10 ** 7]])
    n_faces = np.concatenate([clean, [1, 0]])
    pf, ff, outlier = flag_patch_count_outliers(n_points, n_faces, 2.0, 3.0)
    assert outlier[-1] and outlier[-2]  # points side flags the last, faces side the one with a single face
    assert np.array_equal(outlier, pf.mask | ff.mask)


def test_histogram_png(tmp_path):
    clean, extremes = _sample(2, 1000)
    counts = np.concatenate([clean, extremes])
    fit = fit_count_outliers(counts, 2.0, 3.0)
    path = save_histogram_png(counts, fit, tmp_path / "report" / "faces_hist.png", "faces per patch")
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and data[12:16] == b"IHDR" and len(data) > 5000
    assert [p.name for p in path.parent.iterdir()] == ["faces_hist.png"]  # no temporary left behind
    empty = save_histogram_png(np.zeros(3, int), fit_count_outliers(np.zeros(3, int), 2, 3), tmp_path / "e.png", "t")
    assert empty.read_bytes()[:4] == b"\x89PNG"
