"""Smoke test of benchmarks/partition_bench.py: it runs end to end on a tiny synthetic campus and reports
positive figures. No timing assertions: the figures are the benchmark's business."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "partition_bench.py"


def _load_bench():
    spec = importlib.util.spec_from_file_location("partition_bench", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their module by name
    spec.loader.exec_module(module)
    return module


def test_partition_bench_reports_positive_figures(tmp_path, capsys):
    bench = _load_bench()
    r = bench.main(["--synthetic-points", "160000", "--work", str(tmp_path)])
    out = capsys.readouterr().out

    assert r["errors"] == []
    f = r["figures"]
    assert f["n_points"] == f["baseline_n_points"] == 160_000  # both sides handled every point
    assert f["n_faces"] > 0
    for key in ("ms3d_pw_points_per_s", "ms3d_pw_faces_per_s", "ms3d_stage_points_per_s",
                "baseline_pw_points_per_s"):
        assert math.isfinite(f[key]) and f[key] > 0, key
    # 2 x 2 and 4 x 4 blocks of 100 m (plus slivers where world-anchored patches straddle a block edge)
    assert len(r["rss"]) == 2 and r["rss"][0]["tiles"] >= 4 and r["rss"][1]["tiles"] >= 16
    for row in r["rss"]:
        assert row["peak_rss"] >= row["rss_imports"] > 0
        assert row["baseline_peak_rss"] > 0 and row["n_points"] > 0
    assert "ratio ms3d / baseline" in out and "target >= 3 M points/s" in out and "peak RSS" in out
    assert not list(tmp_path.glob("wd-*"))  # work dirs cleaned, only the reusable inputs kept
