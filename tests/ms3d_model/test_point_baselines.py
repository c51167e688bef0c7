"""PointNet++ and PointCNN (ms3d_model.point_baselines): sampling, grouping, training, and training on any
device (CUDA when present)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from ms3d_model.net import build_net, n_parameters
from ms3d_model.point_baselines import ball_query, farthest_points, gather_points, knn
from ms3d_model.profiles import PROFILES
from ms3d_model.train import load_checkpoint, predict, resolve_device, train_model

from .test_net import _sheet_pairs

TINY = PROFILES["tiny"]


def test_farthest_points_spread_over_the_set_and_start_at_point_zero():
    xyz = torch.tensor([[[0.0, 0, 0], [0.1, 0, 0], [1.0, 0, 0], [0.5, 0, 0], [0.9, 0, 0]]])
    idx = farthest_points(xyz, 3)
    assert idx.tolist() == [[0, 2, 3]]  # 0, then the far end, then the middle
    assert farthest_points(xyz, 9).tolist() == [[0, 1, 2, 3, 4]]


def test_ball_query_keeps_the_near_and_repeats_the_nearest_for_the_rest():
    xyz = torch.tensor([[[0.0, 0, 0], [0.05, 0, 0], [0.5, 0, 0], [2.0, 0, 0]]])
    got = ball_query(xyz, xyz[:, :1], radius=0.1, k=3)
    assert got.tolist() == [[[0, 1, 0]]]
    assert knn(xyz, xyz[:, 3:], 2).tolist() == [[[3, 2]]]
    assert gather_points(xyz, torch.tensor([[2, 0]])).tolist() == [[[0.5, 0, 0], [0.0, 0, 0]]]


@pytest.mark.parametrize("arch", ["pointnet2", "pointcnn"])
def test_a_point_baseline_learns_lifted_points_from_flat_ones(arch, tmp_path):
    train, val = _sheet_pairs(96, seed=2), _sheet_pairs(32, seed=3)
    prof = replace(TINY, net=replace(TINY.net, arch=arch), epochs=6, batch_size=16, lr=0.01, device="cpu")
    res = train_model(prof, train, val, tmp_path, progress=False)
    assert res["device"] == "cpu" and res["parameters"] == n_parameters(build_net(prof.net))
    net, profile, meta = load_checkpoint(tmp_path / "best.pt")
    assert profile.net.arch == arch
    p = predict(net, val)
    assert p[val.labels == 1].mean() > p[val.labels == 0].mean() + 0.05
    assert meta["metrics"]["ap_bad"] >= 0.9  # at chance it is the bad share, 0.5


def test_asking_for_cuda_without_it_is_one_clear_error():
    if torch.cuda.is_available():
        pytest.skip("this machine has CUDA")
    with pytest.raises(ValueError, match="sees no CUDA device"):
        resolve_device("cuda")
    assert resolve_device("auto").type == "cpu"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here")
def test_training_on_cuda_gives_the_cpu_result_within_tolerance(tmp_path):
    train, val = _sheet_pairs(64, seed=2), _sheet_pairs(16, seed=3)
    out = {}
    for dev in ("cpu", "cuda"):
        prof = replace(TINY, net=replace(TINY.net, arch="pointnet"), epochs=2, device=dev)
        train_model(prof, train, val, tmp_path / dev, progress=False)
        net, _, _ = load_checkpoint(tmp_path / dev / "last.pt")  # checkpoints load on the CPU
        out[dev] = predict(net, val)
    np.testing.assert_allclose(out["cuda"], out["cpu"], atol=0.05)
