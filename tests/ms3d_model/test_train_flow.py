"""``ms3d train`` end to end on the tiny campus without a Prefect server, then ``ms3d evaluate`` on it."""

from __future__ import annotations

import json

import numpy as np
import pytest


def test_train_then_evaluate_on_a_processed_campus(tiny_work, tmp_path):
    from flows.evaluate import evaluate, suite_models
    from flows.train import TrainSpec, train
    from ms3d_model.dataset import area_split
    from ms3d_model.train import load_checkpoint
    from tasks.classify import campus_pair_set

    _, wd = tiny_work
    out = tmp_path / "train"
    spec = TrainSpec(out=str(out), data=str(tmp_path / "data"), seeds=[], work_dirs=[str(wd.root)], profile="tiny",
                     overrides={"epochs": 2, "pairs_per_epoch": 64}, models=["ms3dqe", "pointnet", "gbm"], block_m=10.0,
                     progress=False)
    summary = train(spec, use_prefect=False)
    assert set(summary["models"]) == {"ms3dqe", "pointnet", "gbm"}
    assert summary["n_train"] > 0 and summary["n_val"] > 0
    for name in ("ms3dqe", "pointnet"):
        hist = json.loads((out / name / "history.json").read_text())
        assert [h["epoch"] for h in hist] == [1, 2]
        assert (out / name / "curves.png").exists()
        _, prof, meta = load_checkpoint(out / name / "best.pt")
        assert prof.name == f"tiny:{name}" and meta["metrics"]["epoch"] in (1, 2)
        # the kept epoch is the one with the best validation AP on bad, and it ships that epoch's threshold
        best = max(hist, key=lambda h: (h["val_ap_bad"], -h["epoch"]))
        assert meta["metrics"]["epoch"] == best["epoch"] and meta["threshold"] == best["threshold"]
    # the trees learn the tiny campus: AP on bad above the bad share (a random ranking's), recall > 0 at the
    # threshold chosen at precision >= 0.8
    g = summary["models"]["gbm"]["best"]
    bad_share = g["confusion"][1][0] + g["confusion"][1][1]
    assert g["ap_bad"] > bad_share / g["n"] + 0.2 and g["recall_bad"] > 0.3
    assert summary["buffer_m"] > 0 and (out / "gbm" / "best.pt").exists()
    # the split is by area: no validation pair has a training pair in a neighbouring cell column
    ps = campus_pair_set(wd.root, "t", 64, 32, 3, 0)
    tr, va = area_split(ps.ijk, (2.3, 1.0, 0.7), ps.campus, 10.0, 0.2, 0)
    cols_tr = {(int(i), int(j)) for i, j in ps.ijk[tr, :2]}
    for i, j in ps.ijk[va, :2]:
        assert not any((i + di, j + dj) in cols_tr for di in (-1, 0, 1) for dj in (-1, 0, 1))
    res = evaluate(suite_models(str(out)), "tiny", str(wd.root), data=str(tmp_path / "data"), threads=1)
    assert "Table 3" in res["text"] and "Table 4" in res["text"]
    r = res["results"]["ms3dqe"]
    cm = np.array(r["confusion"])
    assert cm.sum() == r["n"] == len(ps) and cm[1].sum() == int((ps.labels == 1).sum())
    assert r["acc"] == pytest.approx(np.trace(cm) / r["n"])  # accuracy is the confusion matrix's diagonal share
    assert r["sec_b1"] > 0 and r["parameters"] > 0
