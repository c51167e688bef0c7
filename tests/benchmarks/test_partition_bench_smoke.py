"""Smoke test of benchmarks/partition_bench.py: it runs end to end on tiny inputs and reports positive
figures. No timing assertions: the figures are the benchmark's business."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "partition_bench.py"


def _load_bench():
    sys.path.insert(0, str(BENCH.parent))
    spec = importlib.util.spec_from_file_location("partition_bench", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their module by name
    spec.loader.exec_module(module)
    return module


def test_partition_bench_reports_positive_figures(tmp_path, capsys):
    bench = _load_bench()
    r = bench.main(["--synthetic-points", "160000", "--big-tile-points", "300000", "--small-tile-points", "100000",
                    "--budget-mb", "64", "--work", str(tmp_path)])
    out = capsys.readouterr().out
    assert r["errors"] == [], r["errors"]
    f = r["figures"]
    assert f["n_points"] == f["baseline_n_points"] == 160_000  # both sides handled every point
    for key in ("decode_ratio", "ingest_ratio_cpu", "ingest_ratio_wall", "e2e_ratio"):
        assert math.isfinite(f[key]) and f[key] > 0, key
    big, small = r["rss"]
    assert big["n"] == 300_000 and big["streamed"] and big["status"] == "done"  # 64 MB: the external merge
    assert small["n"] == 100_000 and big["peak_rss"] > 0
    assert "target >= 0.9x" in out and "target >= 1.5x" in out and "peak RSS of one tile task" in out
