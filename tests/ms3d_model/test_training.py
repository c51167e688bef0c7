"""Training for what repair needs: the threshold chosen on validation, the class-balanced loss,
selection by AP on bad, the validation buffer, the featurise-once cache, and the threshold the grader reads
from the checkpoint."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from torch import nn

from ms3d_model.cues import N_CUES
from ms3d_model.dataset import (
    PairSet,
    PairTensors,
    area_split,
    largest_defect_extent_m,
    load_pair_set,
    save_pair_set,
    to_batch,
)
from ms3d_model.features import featurise_pairs
from ms3d_model.metrics import best_epoch, choose_threshold
from ms3d_model.objectives import FocalLoss, class_weights, make_criterion, make_optimiser
from ms3d_model.profiles import PAPER_TRAINING, PROFILES, Profile
from ms3d_model.train import (
    DEFAULT_THRESHOLD,
    checkpoint_threshold,
    load_checkpoint,
    make_model,
    predict,
    save_checkpoint,
    selection_view,
    train_model,
)

TINY = PROFILES["tiny"]


def test_the_threshold_is_the_best_f1_on_bad_above_the_precision_floor():
    # 10 bad and 30 good pairs; scores rank them: 6 bad on top (0.95..0.90), then 2 good (0.85, 0.84), then
    # 4 bad (0.80..0.77), then the other 28 good below 0.5.
    bad_hi, good_mid, bad_lo = np.linspace(.95, .90, 6), np.array([.85, .84]), np.linspace(.80, .77, 4)
    score = np.r_[bad_hi, good_mid, bad_lo, np.linspace(.45, .01, 28)]
    y = np.r_[np.ones(6), np.zeros(2), np.ones(4), np.zeros(28)].astype(int)
    # at 0.77 every bad is found with precision 10/12 = 0.833, F1 0.909: the optimum at floor 0.8
    c = choose_threshold(y, score, 0.80)
    assert c["threshold"] == pytest.approx(0.77) and c["recall"] == 1.0
    assert c["precision"] == pytest.approx(10 / 12) and c["f1"] == pytest.approx(2 * (10 / 12) / (1 + 10 / 12))
    assert c["floor_met"]
    # a floor of 0.9 excludes it: only the top six (precision 1, recall 0.6) qualify
    c = choose_threshold(y, score, 0.90)
    assert c["threshold"] == pytest.approx(0.90) and c["precision"] == 1.0 and c["recall"] == pytest.approx(0.6)
    # the grades at the chosen threshold reproduce its figures
    pred = score >= c["threshold"]
    assert (pred & (y == 1)).sum() == 6 and pred.sum() == 6
    # unreachable floor: the best F1 overall, flagged
    noisy = choose_threshold(np.array([0, 1, 1, 0]), np.array([.9, .8, .7, .6]), 0.99)
    assert not noisy["floor_met"] and noisy["threshold"] == pytest.approx(0.7)
    assert choose_threshold(np.zeros(5, int), np.linspace(0, 1, 5))["threshold"] == DEFAULT_THRESHOLD


def test_balanced_loss_weights_give_each_class_the_same_total_weight():
    y = np.r_[np.zeros(30), np.ones(10)].astype(np.int8)
    w = class_weights(y)
    assert w[1] == pytest.approx(3 * w[0]) and w[0] * 30 + w[1] * 10 == pytest.approx(40)
    assert class_weights(np.zeros(4, int)).tolist() == [1.0, 1.0]  # an absent class keeps weight 1
    logits = torch.tensor([[2.0, -1.0], [0.5, 0.3], [-1.0, 1.5], [0.0, 0.0]])
    t = torch.tensor([0, 0, 1, 1])
    crit = make_criterion("balanced", y)
    logp = torch.log_softmax(logits, 1)[torch.arange(4), t]
    ws = torch.from_numpy(w)[t]
    assert float(crit(logits, t)) == pytest.approx(float(-(ws * logp).sum() / ws.sum()), rel=1e-6)
    # focal with gamma 0 is the weighted log-loss averaged over pairs; gamma > 0 down-weights easy pairs
    f0 = FocalLoss(torch.from_numpy(w), 0.0)
    assert float(f0(logits, t)) == pytest.approx(float(-(ws * logp).mean()), rel=1e-6)
    assert float(make_criterion("focal", y, 2.0)(logits, t)) < float(f0(logits, t))
    assert isinstance(make_criterion("ce", y), nn.CrossEntropyLoss) and make_criterion("ce", y).weight is None
    with pytest.raises(ValueError, match="unknown loss"):
        make_criterion("hinge", y)


def test_selection_picks_the_best_ap_on_bad_not_the_best_accuracy():
    # epoch 2 sits at the majority class (best accuracy, no ranking); epoch 3 finds the bad pairs
    history = [{"epoch": 1, "val_acc": 0.70, "val_ap_bad": 0.40, "val_f1_bad": 0.30, "val_map": 0.55},
               {"epoch": 2, "val_acc": 0.80, "val_ap_bad": 0.25, "val_f1_bad": float("nan"), "val_map": 0.52},
               {"epoch": 3, "val_acc": 0.76, "val_ap_bad": 0.71, "val_f1_bad": 0.66, "val_map": 0.80},
               {"epoch": 4, "val_acc": 0.78, "val_ap_bad": 0.65, "val_f1_bad": 0.69, "val_map": 0.78}]
    rows = [selection_view(h) for h in history]
    assert best_epoch(rows, "ap_bad") == 2 and best_epoch(rows, "acc") == 1
    assert best_epoch(rows, "f1_bad") == 3 and best_epoch(rows, "map") == 2
    with pytest.raises(ValueError):
        best_epoch(rows, "loss")


def test_the_validation_buffer_is_the_largest_defect_and_keeps_defects_on_one_side():
    # one campus row of 60 x 6 cells; a 4-cell-long defect (9.2 m) and single-cell ones
    i, j = np.meshgrid(np.arange(60), np.arange(6), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), np.zeros(i.size, int)], 1)
    labels = np.zeros(len(ijk), np.int8)
    labels[(ijk[:, 0] >= 10) & (ijk[:, 0] < 14) & (ijk[:, 1] == 2)] = 1
    labels[(ijk[:, 0] == 40) & (ijk[:, 1] == 4)] = 1
    size = (2.3, 1.0, 0.7)
    buf = largest_defect_extent_m(ijk, labels, size)
    assert buf == pytest.approx(4 * 2.3)
    assert largest_defect_extent_m(ijk, labels, size, cap_m=5.0) == 5.0
    campus = np.zeros(len(ijk), int)
    tr0, va0 = area_split(ijk, size, campus, 20.0, 0.3, 0)
    tr, va = area_split(ijk, size, campus, 20.0, 0.3, 0, buffer_m=buf)
    np.testing.assert_array_equal(va, va0)
    assert not (tr & va).any() and tr.sum() < tr0.sum()
    xy = (ijk[:, :2] + 0.5) * size[:2]
    gap = np.min(np.linalg.norm(xy[tr][:, None] - xy[va][None], axis=2))
    assert gap > buf  # farther apart than the largest defect is long


def _pairs(n: int, seed: int, bad_every: int = 4, lift: float = 0.4) -> PairSet:
    """n pairs: a nearly flat welded grid of faces and points on it; every ``bad_every``-th pair ("bad") has
    its points lifted off the faces by ``lift`` (pair units). 1 in ``bad_every`` bad."""
    rng = np.random.default_rng(seed)
    pts, tris = [], []
    labels = (np.arange(n) % bad_every == 0).astype(np.int8)
    for i in range(n):
        k = int(rng.integers(3, 6))
        x, y = np.meshgrid(np.linspace(-1, 1, k + 1), np.linspace(-1, 1, k + 1), indexing="ij")
        v = np.stack([x, y, 0.02 * rng.standard_normal(x.shape)], axis=-1)
        a, b, c, d = v[:-1, :-1], v[1:, :-1], v[1:, 1:], v[:-1, 1:]
        t = np.concatenate([np.stack([a, b, c], -2), np.stack([a, c, d], -2)]).reshape(-1, 3, 3)
        m = int(rng.integers(20, 100))
        p = np.einsum("mv,mvc->mc", rng.dirichlet(np.ones(3), size=m), t[rng.integers(len(t), size=m)])
        p[:, 2] += labels[i] * lift
        pts.append(p), tris.append(t)
    feats = featurise_pairs(pts, tris, None, np.arange(n), TINY.max_points, TINY.max_faces, TINY.k_centre)
    return PairSet(feats, np.zeros((n, N_CUES), np.float32), labels, np.zeros((n, 3), np.int64),
                   np.zeros(n, np.int16), ("toy",))


def test_tensors_give_the_same_batches_as_the_arrays():
    ps = _pairs(6, seed=4)
    pt = PairTensors.from_pairs(ps.compact())
    a, b = to_batch(ps.compact().feats.take(np.array([4, 1]))), pt.batch([4, 1])
    assert set(a) == set(b)
    for k in a:
        assert a[k].dtype == b[k].dtype
        torch.testing.assert_close(a[k], b[k])


def test_a_short_run_from_the_cache_learns_past_the_majority_class_and_ships_its_threshold(tmp_path):
    torch.set_num_threads(1)
    save_pair_set(_pairs(128, seed=1).compact(), tmp_path / "train.npz")  # featurised once ...
    save_pair_set(_pairs(64, seed=2).compact(), tmp_path / "val.npz")
    train, val = load_pair_set(tmp_path / "train.npz"), load_pair_set(tmp_path / "val.npz")  # ... trained from the cache
    assert len(train) == 128 and train.labels.mean() == 0.25
    prof = replace(TINY, epochs=6, lr=5e-3, pairs_per_epoch=None)
    assert (prof.optimizer, prof.schedule, prof.loss, prof.select_by) == ("adamw", "onecycle", "balanced", "ap_bad")
    res = train_model(prof, train, val, tmp_path / "run", progress=False)
    net, _, meta = load_checkpoint(tmp_path / "run" / "best.pt")
    thr = checkpoint_threshold(meta)
    assert thr == res["threshold"] == meta["metrics"]["threshold"]
    pred = predict(net, val) >= thr
    y = val.labels == 1
    majority = max(y.mean(), 1 - y.mean())
    assert (pred == y).mean() >= majority + 0.15  # the majority class scores 0.75 here
    assert pred[y].mean() >= 0.8 and (y[pred].mean() if pred.any() else 0) >= 0.8
    # the kept epoch is the best AP on bad of the history
    hist = res["history"]
    assert meta["metrics"]["epoch"] == max(hist, key=lambda h: (h["val_ap_bad"], -h["epoch"]))["epoch"]


def test_the_checkpoint_round_trips_its_threshold_and_old_ones_grade_at_one_half(tmp_path):
    from tasks.classify import grading_threshold, load_model
    from tasks.config.classify import ClassifyConfig

    net = make_model(TINY)
    save_checkpoint(tmp_path / "m.pt", net, TINY, threshold=0.3125)
    _, _, meta = load_checkpoint(tmp_path / "m.pt")
    assert checkpoint_threshold(meta) == 0.3125 and load_model(str(tmp_path / "m.pt")).threshold == 0.3125
    assert grading_threshold(ClassifyConfig(model=str(tmp_path / "m.pt"))) == 0.3125
    assert grading_threshold(ClassifyConfig(model=str(tmp_path / "m.pt"), threshold=0.7)) == 0.7  # the config wins
    raw = torch.load(tmp_path / "m.pt", weights_only=True)
    del raw["threshold"]  # as written before thresholds shipped
    torch.save(raw, tmp_path / "old.pt")
    assert load_model(str(tmp_path / "old.pt")).threshold == DEFAULT_THRESHOLD
    with pytest.raises(ValueError, match="not a probability"):
        save_checkpoint(tmp_path / "bad.pt", net, TINY, threshold=1.5)
    # a profile written before the training switches existed reads as trained the paper's way
    old = TINY.to_json()
    for k in ("optimizer", "schedule", "loss", "focal_gamma", "select_by", "min_precision"):
        old.pop(k)
    assert Profile.from_json(old).optimizer == PAPER_TRAINING["optimizer"]


def test_the_paper_switch_builds_sgd_with_multistep():
    net = nn.Linear(2, 2)
    opt, sched, per_step = make_optimiser(replace(TINY, **PAPER_TRAINING), net.parameters(), 100)
    assert isinstance(opt, torch.optim.SGD) and isinstance(sched, torch.optim.lr_scheduler.MultiStepLR) and not per_step
    opt, sched, per_step = make_optimiser(TINY, net.parameters(), 100)
    assert isinstance(opt, torch.optim.AdamW) and isinstance(sched, torch.optim.lr_scheduler.OneCycleLR) and per_step


def test_the_classify_stage_grades_at_the_checkpoints_threshold(tiny_work, tmp_path):
    import shutil

    from storage.patches.read import PatchStore
    from storage.workdir.layout import WorkDir
    from tasks.classify import run_classify_tile

    cfg, shared = tiny_work
    wd = WorkDir(shutil.copytree(shared.root, tmp_path / "work"))  # the fixture stays read-only
    cfg = cfg.model_copy(update={"work_dir": str(wd.root)})
    torch.manual_seed(0)
    save_checkpoint(tmp_path / "zero.pt", make_model(TINY), TINY, threshold=0.0)  # every pair is bad at 0
    ccfg = cfg.classify.model_copy(update={"enabled": True, "model": str(tmp_path / "zero.pt"), "evidence": False,
                                           "threshold": None})
    tile = max(wd.live_tiles(), key=lambda t: int(((lambda p: (p["n_faces"] > 0) & (p["n_points"] > 0))(
        PatchStore(wd.tile_dir(t)).patches())).sum()))  # the tile with the most pairs
    res = run_classify_tile(tile, cfg.model_copy(update={"classify": ccfg}), wd)
    assert res["status"] == "done"
    store = PatchStore(wd.tile_dir(tile))
    g, p = store.side("grades"), store.patches()
    pair = (p["n_faces"] > 0) & (p["n_points"] > 0)
    assert pair.any() and (g["grade"][pair] == 1).all() and np.isfinite(g["score"][pair]).all()
    res = run_classify_tile(tile, cfg.model_copy(update={"classify": ccfg.model_copy(update={"threshold": 1.0})}), wd)
    g = PatchStore(wd.tile_dir(tile)).side("grades")
    assert not res["skipped"] and (g["grade"][pair] == (g["score"][pair] >= 1.0)).all() and (g["grade"][pair] == 0).any()
