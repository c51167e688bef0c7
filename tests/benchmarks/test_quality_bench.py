"""quality_bench's evaluation: seen / unseen split and exact aggregation of per-class sums."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location("quality_bench", Path(__file__).parents[2] / "benchmarks" / "quality_bench.py")
qb = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(qb)


def test_seen_scope_counts_only_the_seen_facade():
    # truth: two 2 x 2 m walls (class 2 = wall) side by side; the prediction covers the first one, 3 cm off
    v = np.array([[0, 0, 0], [2, 0, 0], [2, 0, 2], [0, 0, 2], [2, 0, 0], [4, 0, 0], [4, 0, 2], [2, 0, 2]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    cls = np.full(4, 2)
    seen = np.array([True, True, False, False])
    pred_v = v[:4] + [0, 0.03, 0]
    r = qb.evaluate(pred_v, f[:2], (v, f, cls), seen, spacing_m=0.05)
    assert r["seen"]["F5"] == pytest.approx(1.0) and r["seen"]["uncovered"] == pytest.approx(0.0)
    assert r["all"]["F5"] == pytest.approx(2 / 3, abs=0.01)  # precision 1, recall 1/2
    assert r["all"]["uncovered"] == pytest.approx(0.5, abs=0.01)
    assert r["seen"]["acc_m"] == pytest.approx(0.03, abs=1e-3)
    assert r["all"]["per_class"]["wall"]["F5"] == pytest.approx(r["all"]["F5"])
