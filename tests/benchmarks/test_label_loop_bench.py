"""Smoke test of benchmarks/label_loop_bench.py on the tiny synth campus (the session's ``tiny_work``): the
simulated user labels the least-sure pairs with their truth, the fine-tune runs, and the figures are those of
the pairs the user did not label.

It grades the tiny campus twice and featurises it once more for the fine-tune's synth mix (3 x ~1,600 pairs of
cue extraction + a tree fit): 35-60 s on this loaded 2-core machine, over the suite's 20 s per test. So it
runs only with ``MS3D_BENCH_SMOKE=1`` (``MS3D_BENCH_SMOKE=1 python -m pytest -q tests/benchmarks/test_label_loop_bench.py``).
"""

from __future__ import annotations

import csv
import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

pytestmark = [pytest.mark.slow, pytest.mark.skipif(os.environ.get("MS3D_BENCH_SMOKE") != "1",
                                                   reason="35-60 s: set MS3D_BENCH_SMOKE=1 to run it")]


def test_label_loop_bench_labels_least_sure_truth_and_scores_the_rest(tiny_work, tmp_path, capsys):
    import label_loop_bench as bench

    from storage.grid import PatchGrid
    from storage.patches.read import PatchStore
    from storage.workdir.layout import WorkDir

    cfg0, wd0 = tiny_work
    work = tmp_path / "work"
    shutil.copytree(wd0.root, work, ignore=shutil.ignore_patterns("labels", "grades.parquet"))
    config = tmp_path / "in.yaml"
    doc = cfg0.model_dump(mode="json")
    doc["classify"]["evidence"] = False  # the geometric evidence is not what this test is about: seconds saved
    config.write_text(yaml.safe_dump(doc))
    n = 12
    s = bench.main(["--config", str(config), "--work", str(work), "--out", str(tmp_path / "out"), "--n-labels",
                    str(n), "--data", str(tmp_path / "data"), "--seeds", "--mix-work-dir", str(work)])
    printed = capsys.readouterr().out
    assert "| shipped, score >= " in printed and "fine-tune:" in printed

    # the CSV holds n rows, each the truth label of its patch
    rows = [r for p in sorted((work / "labels").glob("*.csv")) for r in csv.DictReader(p.read_text().splitlines())]
    assert len(rows) == n == s["n_labels"] and all(r["time"].endswith("+00:00") for r in rows)
    wd = WorkDir(work)
    truth, graded = {}, {}
    for t in wd.live_tiles():
        st = PatchStore(wd.tile_dir(t))
        keys = st.patches()["patch"]
        truth.update(zip(keys.tolist(), st.side("labels")["label"].tolist()))
        graded.update(zip(keys.tolist(), st.side("grades")["score"].tolist()))
    user = PatchGrid.pack(np.array([[int(r[c]) for c in "ijk"] for r in rows], np.int64))
    assert [truth[k] for k in user.tolist()] == [int(r["label"]) for r in rows]
    assert 0 < sum(int(r["label"]) for r in rows) < n or len({truth[k] for k in truth}) == 1

    # the figures are over the other truth-labelled pairs: the after grades on disk give the same recall
    rest = [k for k, v in graded.items() if np.isfinite(v) and k not in set(user.tolist())]
    after = s["rows"][next(r for r in s["rows"] if r.startswith("fine-tuned, score") and "own" in r)]
    assert after["n"] == len(rest)
    thr = float(s["finetune"]["validation"]["threshold"])
    y = np.array([truth[k] for k in rest]) == 1
    pred = np.array([graded[k] for k in rest]) >= thr
    assert after["n_bad"] == int(y.sum()) and after["recall"] == (y & pred).sum() / max(int(y.sum()), 1)
    assert Path(s["finetune"]["checkpoint"]).exists() and s["walls"]["finetune_s"] > 0
