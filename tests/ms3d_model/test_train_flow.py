"""``ms3d train`` end to end on the tiny campus without a Prefect server, then ``ms3d evaluate`` on it."""

from __future__ import annotations

import json

import numpy as np


def test_train_then_evaluate_on_a_processed_campus(tiny_work, tmp_path):
    from flows.evaluate import evaluate, suite_models
    from flows.train import TrainSpec, train
    from ms3d_model.dataset import area_split
    from ms3d_model.train import load_checkpoint
    from tasks.classify import campus_pair_set

    _, wd = tiny_work
    out = tmp_path / "train"
    spec = TrainSpec(out=str(out), data=str(tmp_path / "data"), seeds=[], work_dirs=[str(wd.root)], profile="tiny",
                     overrides={"epochs": 2, "pairs_per_epoch": 64}, models=["ms3dqe", "pointnet"], block_m=10.0,
                     progress=False)
    summary = train(spec, use_prefect=False)
    assert set(summary["models"]) == {"ms3dqe", "pointnet"}
    assert summary["n_train"] > 0 and summary["n_val"] > 0
    for name in ("ms3dqe", "pointnet"):
        hist = json.loads((out / name / "history.json").read_text())
        assert [h["epoch"] for h in hist] == [1, 2]
        assert (out / name / "curves.png").exists()
        _, prof, meta = load_checkpoint(out / name / "best.pt")
        assert prof.name == f"tiny:{name}" and meta["metrics"]["epoch"] in (1, 2)
    # the split is by area: no validation pair has a training pair in a neighbouring cell column
    ps = campus_pair_set(wd.root, "t", 64, 32, 3, 0)
    tr, va = area_split(ps.ijk, (2.3, 1.0, 0.7), ps.campus, 10.0, 0.2, 0)
    cols_tr = {(int(i), int(j)) for i, j in ps.ijk[tr, :2]}
    for i, j in ps.ijk[va, :2]:
        assert not any((i + di, j + dj) in cols_tr for di in (-1, 0, 1) for dj in (-1, 0, 1))
    res = evaluate(suite_models(str(out)), "tiny", str(wd.root), data=str(tmp_path / "data"), threads=1)
    assert "Table 3" in res["text"] and "Table 4" in res["text"]
    r = res["results"]["ms3dqe"]
    assert 0 <= r["acc"] <= 1 and r["sec_b1"] > 0 and r["parameters"] > 0
    assert np.array(r["confusion"]).sum() == r["n"]
