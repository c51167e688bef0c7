"""Every network variant runs forward and backward; outputs ignore the order of points and faces; a short
training run lowers the loss; checkpoints load with weights_only=True."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from ms3d_model.cues import N_CUES
from ms3d_model.dataset import PairSet, to_batch
from ms3d_model.features import featurise_pairs
from ms3d_model.net import (
    ABLATIONS,
    MESHNET,
    PAPER_PARAMETERS,
    NetConfig,
    build_net,
    kernel_response_stats,
    n_parameters,
)
from ms3d_model.profiles import PROFILES
from ms3d_model.train import load_checkpoint, predict, save_checkpoint, train_model

TINY = PROFILES["tiny"]
VARIANTS = {**{f"ablation {k}": v for k, v in ABLATIONS.items()}, "meshnet": MESHNET,
            "ms3dqe+": {"n_cues": N_CUES}, "pointnet": {"arch": "pointnet"}}


def _pairs(n: int, seed: int = 0, bad_shift: float = 0.0):
    """n random pairs: a wavy sheet of faces and points on it; 'bad' pairs have their points moved off."""
    rng = np.random.default_rng(seed)
    pts, tris, labels = [], [], []
    for i in range(n):
        m = int(rng.integers(6, 40))
        base = rng.uniform(-1, 1, size=(m, 1, 3)) * [1, 1, 0.1]
        t = base + rng.normal(scale=0.2, size=(m, 3, 3)) * [1, 1, 0.05]
        bad = i % 2
        p = rng.uniform(-1, 1, size=(int(rng.integers(5, 100)), 3)) * [1, 1, 0.05]
        p[:, 2] += bad * bad_shift
        pts.append(p), tris.append(t), labels.append(bad)
    feats = featurise_pairs(pts, tris, None, np.arange(n), TINY.max_points, TINY.max_faces, TINY.k_centre)
    cues = rng.normal(size=(n, N_CUES)).astype(np.float32)
    return PairSet(feats, cues, np.array(labels, np.int8), np.zeros((n, 3), np.int64), np.zeros(n, np.int16), ("t",))


@pytest.mark.parametrize("name", list(VARIANTS))
def test_every_variant_runs_forward_and_backward(name):
    torch.manual_seed(0)
    net = build_net(replace(TINY.net, **VARIANTS[name]))
    ps = _pairs(4)
    out = net(to_batch(ps.feats, ps.cues))
    assert out.shape == (4, 2)
    out.logsumexp(1).mean().backward()
    grads = [p.grad for p in net.parameters() if p.requires_grad]
    assert all(g is not None for g in grads) and any(float(g.abs().sum()) > 0 for g in grads)


@pytest.mark.parametrize("name", ["ablation Full", "ms3dqe+", "meshnet", "ablation (4)"])
def test_permuting_points_and_faces_leaves_the_output_unchanged(name):
    torch.manual_seed(0)
    net = build_net(replace(TINY.net, **VARIANTS[name])).eval()
    ps = _pairs(3, seed=1)
    b = to_batch(ps.feats, ps.cues)
    rng = np.random.default_rng(5)
    pp = torch.from_numpy(rng.permutation(b["points"].shape[1]))
    pf = torch.from_numpy(rng.permutation(b["centres"].shape[1]))
    inv = torch.argsort(pf)  # old face index -> new position
    perm = {k: v for k, v in b.items()}
    perm["points"] = b["points"][:, pp]
    for k in ("centres", "normals", "corners"):
        perm[k] = b[k][:, pf]
    for k in ("face_nbr", "centre_knn"):
        perm[k] = inv[b[k][:, pf]]
    with torch.no_grad():
        torch.testing.assert_close(net(perm), net(b), rtol=1e-4, atol=1e-5)


def test_paper_sizes_parameter_count_is_close_to_the_paper():
    n = n_parameters(build_net(NetConfig()))
    assert abs(n - PAPER_PARAMETERS) / PAPER_PARAMETERS < 0.05
    meshnet = n_parameters(build_net(NetConfig(**MESHNET)))
    assert abs(meshnet - 4_254_631) / 4_254_631 < 0.02  # the paper's Table 3 MeshNet


def test_kernel_correlation_is_alive_at_the_chosen_sigma_and_dead_at_the_papers():
    torch.manual_seed(0)
    net = build_net(TINY.net)
    ps = _pairs(4)
    st = kernel_response_stats(net, to_batch(ps.feats), sigmas=(0.005, None))
    assert st["normal@0.005"]["frac_gt_1e-3"] < 0.05 and st["centre@0.005"]["frac_gt_1e-3"] < 0.2
    assert st[f"normal@{TINY.net.sigma_normal:g}"]["frac_gt_1e-3"] > 0.2
    assert st[f"centre@{TINY.net.sigma_centre:g}"]["frac_gt_1e-3"] > 0.5


def test_short_training_lowers_the_loss_and_checkpoints_load_weights_only(tmp_path):
    train, val = _pairs(64, seed=2, bad_shift=0.5), _pairs(16, seed=3, bad_shift=0.5)
    prof = replace(TINY, epochs=4, milestones=(10,), lr=0.01)
    res = train_model(prof, train, val, tmp_path, progress=False)
    losses = [h["train_loss"] for h in res["history"]]
    assert losses[-1] < losses[0]
    assert (tmp_path / "curves.png").stat().st_size > 0
    raw = torch.load(tmp_path / "best.pt", weights_only=True)  # plain tensors and containers only
    assert raw["format"] == "ms3d-model/1"
    net, profile, _ = load_checkpoint(tmp_path / "best.pt")
    assert profile == prof and not net.training
    p1 = predict(net, val)
    net2, _, _ = load_checkpoint(tmp_path / "best.pt")
    np.testing.assert_array_equal(p1, predict(net2, val))
    h = save_checkpoint(tmp_path / "again.pt", net, profile)
    assert len(h) == 64


def test_gbm_ships_as_a_tree_net_with_the_same_probabilities(tmp_path):
    from ms3d_model.gbm import fit_gbm, gbm_p_bad, tree_arrays, tree_depth

    rng = np.random.default_rng(0)
    x = rng.normal(size=(600, N_CUES)).astype(np.float32)
    y = (x[:, 0] + x[:, 1] ** 2 > 1).astype(int)
    x[rng.random(x.shape) < 0.02] = np.nan  # missing values take the trees' learned side
    clf = fit_gbm(x, y, max_iter=30)
    arrays = tree_arrays(clf)
    cfg = replace(TINY.net, arch="gbm", n_cues=N_CUES, tree_depth=tree_depth(arrays))
    net = build_net(cfg, {k: torch.from_numpy(v) for k, v in arrays.items()})
    save_checkpoint(tmp_path / "gbm.pt", net, replace(TINY, net=cfg))
    loaded, _, _ = load_checkpoint(tmp_path / "gbm.pt")
    p = torch.softmax(loaded({"cues": torch.from_numpy(x)}), 1)[:, 1].numpy()
    np.testing.assert_allclose(p, gbm_p_bad(clf, x), atol=1e-6)
