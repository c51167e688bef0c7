"""``ms3d evaluate``: every row of Tables 3 and 4 names the model that produced it, and the figures of one kind
of model never sit in another's row (the shipped default, the trees, was once printed as MS3DQE-Net)."""

from __future__ import annotations

from ms3d_model.report import model_kind, model_label, per_class, table3, table4

GBM = {"arch": "gbm", "n_cues": 25}
NET = {"arch": "ms3dqe", "points": True, "face": True, "centre_global": True, "centre_local": True,
       "kernel_correlation": True, "point_aggregation": True, "n_cues": 0, "corners": "edges"}


def _result(acc: float, net: dict, path: str) -> dict:
    return {"acc": acc, "map": acc - 0.01, "parameters": 1234, "sec_b1": 0.001, "sec_best": 0.0005, "best_batch": 64,
            "net": net, "path": path, "precision_good": 0.9, "precision_bad": 0.8, "recall_good": 0.95,
            "recall_bad": 0.7, "f1_good": 0.92, "f1_bad": 0.75, "confusion": [[9, 1], [3, 7]], "n": 20}


def _row(text: str, method: str) -> str:
    return next(line for line in text.splitlines() if line.startswith(method))


def test_trees_passed_as_the_network_stay_in_their_own_row():
    results = {"ms3dqe": _result(0.925, GBM, "ms3d_model/weights/default.pt")}
    t3 = table3(results)
    assert "92.5" not in _row(t3, "MS3DQE-Net ") and _row(t3, "MS3DQE-Net ").rstrip().endswith("-")
    gbm = _row(t3, "GBM on cues")
    assert "92.5" in gbm and gbm.rstrip().endswith("GBM trees (default.pt)")
    t4 = table4({"Full": results["ms3dqe"]}, {"Full": GBM})
    assert "92.5" not in t4 and "no MS3DQE-Net checkpoint scored" in t4
    assert "GBM trees (default.pt)" in per_class(results)


def test_every_row_of_ours_names_its_checkpoint():
    results = {"ms3dqe": _result(0.801, NET, "w/ms3dqe.pt"), "gbm": _result(0.925, GBM, "suite/gbm/best.pt"),
               "ms3dqe_plus": _result(0.856, NET | {"n_cues": 25}, "w/ms3dqe_plus.pt")}
    t3 = table3(results)
    net = _row(t3, "MS3DQE-Net ")
    assert "80.1" in net and net.rstrip().endswith("MS3DQE-Net (ms3dqe.pt)")
    assert _row(t3, "GBM on cues").rstrip().endswith("GBM trees (gbm/best.pt)")
    assert _row(t3, "MS3DQE-Net+").rstrip().endswith("MS3DQE-Net+ (ms3dqe_plus.pt)")
    for line in t3.splitlines()[3:]:  # every row: our figures and a model name, or neither
        has_figures = line[68:77].strip() not in ("", "-")
        assert has_figures == (not line.rstrip().endswith("  -")), line
    t4 = table4({"Full": results["ms3dqe"]}, {"Full": NET})
    assert "80.1" in _row(t4, "Acc (%) ours") and "Full MS3DQE-Net (ms3dqe.pt)" in t4


def test_the_kind_comes_from_the_architecture():
    assert model_kind(GBM) == "gbm" and model_kind(NET) == "ms3dqe"
    assert model_kind(NET | {"face": False}) == "ablation"
    assert model_kind(NET | {"corners": "meshnet", "points": False}) == "meshnet"
    assert model_label({"arch": "pointnet"}, "/x/pointnet/best.pt") == "PointNet (pointnet/best.pt)"


def test_evaluate_with_the_shipped_default_reports_it_as_trees(tiny_work, tmp_path):
    """What ``ms3d evaluate --work-dir W`` (no --model) runs: the default checkpoint passed as "ms3dqe"."""
    from flows.evaluate import evaluate
    from tasks.classify import DEFAULT_MODEL

    _, wd = tiny_work
    res = evaluate({"ms3dqe": str(DEFAULT_MODEL)}, "tiny", str(wd.root), data=str(tmp_path), max_pairs=300)
    assert list(res["results"]) == ["gbm"] and res["results"]["gbm"]["passed_as"] == "ms3dqe"
    text = res["text"]
    acc = f"{100 * res['results']['gbm']['acc']:.1f}"
    assert _row(text, "GBM on cues").rstrip().endswith("GBM trees (default.pt)") and acc in _row(text, "GBM on cues")
    assert _row(text, "MS3DQE-Net ").rstrip().endswith("-") and acc not in _row(text, "MS3DQE-Net ")
    assert "no MS3DQE-Net checkpoint scored" in text


def test_evaluate_grades_at_the_checkpoints_own_threshold(tiny_work, tmp_path):
    """Acc and P/R on bad come from the threshold the checkpoint ships (not 0.5), and the text prints it."""
    import numpy as np
    import torch

    from flows.evaluate import evaluate
    from ms3d_model.metrics import classification_report
    from tasks.classify import DEFAULT_MODEL, campus_pair_set

    _, wd = tiny_work
    obj = torch.load(DEFAULT_MODEL, map_location="cpu", weights_only=True)
    obj["threshold"] = 0.05  # far from 0.5: many more pairs graded bad
    torch.save(obj, tmp_path / "low.pt")
    res = evaluate({"gbm": str(tmp_path / "low.pt")}, "tiny", str(wd.root), data=str(tmp_path), max_pairs=300)
    r = res["results"]["gbm"]
    assert r["threshold"] == 0.05 and "thr 0.050" in res["text"]
    from ms3d_model.train import load_checkpoint, predict

    net, prof, _ = load_checkpoint(tmp_path / "low.pt")
    ps = campus_pair_set(str(wd.root), "tiny", prof.max_points, prof.max_faces, prof.k_centre, prof.seed,
                         cache_dir=str(tmp_path / "cache"))
    ps = ps.take(np.sort(np.random.default_rng(0).permutation(len(ps))[:300])) if len(ps) > 300 else ps
    p = predict(net, ps, 256)
    assert r["confusion"] == classification_report(ps.labels, p, 0.05)["confusion"]
    assert r["confusion"] != classification_report(ps.labels, p, 0.5)["confusion"]


def test_evaluate_scores_the_shipped_path_beside_the_model(tiny_work, tmp_path):
    """The stored grades (model + evidence + user labels) are scored against the labels beside the model
    alone: a patch an override graded bad counts as flagged though its score is low."""
    import json
    import shutil

    import numpy as np
    import pandas as pd
    import pyarrow as pa
    import pyarrow.parquet as pq

    from flows.evaluate import evaluate
    from storage.workdir.layout import WorkDir
    from tasks.classify import DEFAULT_MODEL

    _, wd = tiny_work
    work = tmp_path / "work"
    shutil.copytree(wd.root, work)
    forced = []
    for t in WorkDir(work).live_tiles():
        td = WorkDir(work).tile_dir(t)
        keys = pd.read_parquet(td / "patches.parquet", columns=["patch"])["patch"].to_numpy()
        grade = np.zeros(len(keys), np.int8)
        grade[::7] = 1  # what the evidence rule or a user label graded bad
        forced.append(keys[::7])
        table = pa.table({"patch": keys, "score": np.full(len(keys), 0.01, np.float32), "grade": grade})
        meta = {"grader": "test grader", "model": "x.pt", "threshold": 0.3}
        pq.write_table(table.replace_schema_metadata({"ms3d": json.dumps(meta)}), td / "grades.parquet")
    res = evaluate({"gbm": str(DEFAULT_MODEL)}, "tiny", str(work), data=str(tmp_path))
    sp = res["shipped_path"]
    assert sp["grader"] == "test grader" and sp["threshold"] == 0.3
    assert sp["all"]["n"] == res["results"]["gbm"]["n"]
    cm = np.asarray(sp["all"]["confusion"])
    assert cm[:, 1].sum() == sp["all"]["flagged"] > 0
    assert sp["all"]["flagged"] <= sum(len(f) for f in forced)
    assert 0 < sp["facade"]["n"] < sp["all"]["n"]
    assert "shipped path: test grader" in res["text"]


def test_the_spread_over_campuses():
    from flows.evaluate_path import spread, spread_table, with_flagged

    s = spread([{"ap_bad": 0.8}, {"ap_bad": 0.9}, {"ap_bad": float("nan")}])["ap_bad"]
    assert s["n"] == 2 and abs(s["mean"] - 0.85) < 1e-12 and (s["min"], s["max"]) == (0.8, 0.9)
    assert with_flagged({"confusion": [[8, 2], [1, 9]]})["flagged_share"] == 11 / 20
    text = spread_table({"a": {"m": {"all": {"ap_bad": 0.8}}}, "b": {"m": {"all": {"ap_bad": 0.9}}}})
    assert "Across 2 campuses (a, b)" in text and "0.850 [0.800, 0.900]" in text
