"""The classify stage on the tiny synth campus: grades for every pair, unknown for the rest, resumable."""

from __future__ import annotations

import numpy as np
import torch

from ms3d_model.profiles import PROFILES
from ms3d_model.train import make_model, save_checkpoint
from storage.patch_store import PatchStore


def _checkpoint(path, seed=0):
    torch.manual_seed(seed)
    prof = PROFILES["tiny"]
    return save_checkpoint(path, make_model(prof), prof)


def test_classify_grades_every_pair_then_skips_and_regrades_for_a_new_model(tiny_work, tmp_path):
    from tasks.classify import run_classify_tile

    cfg, wd = tiny_work
    h1 = _checkpoint(tmp_path / "m1.pt", 0)
    cfg = cfg.model_copy(update={"classify": cfg.classify.model_copy(update={"enabled": True, "model": str(tmp_path / "m1.pt"),
                                                                                 "evidence": False})})
    tiles = wd.live_tiles()
    assert tiles
    n_pairs = 0
    for t in tiles:
        res = run_classify_tile(t, cfg, wd)
        assert res["status"] == "done" and not res["skipped"] and res["model_hash"] == h1
        store = PatchStore(wd.tile_dir(t))
        p = store.patches()
        g = store.side("grades")
        pair = (p["n_faces"] > 0) & (p["n_points"] > 0)
        n_pairs += int(pair.sum())
        assert set(np.unique(g["grade"][pair]).tolist()) <= {0, 1}
        assert np.isfinite(g["score"][pair]).all() and ((g["score"][pair] >= 0) & (g["score"][pair] <= 1)).all()
        np.testing.assert_array_equal(g["grade"][pair], (g["score"][pair] >= 0.5).astype(np.int8))
        # faces without points and points without faces: unknown, no score
        assert (g["grade"][~pair] == -1).all() and np.isnan(g["score"][~pair]).all()
        assert res["n_pairs"] == pair.sum() and res["n_unknown"] == (~pair).sum()
    assert n_pairs > 0
    again = [run_classify_tile(t, cfg, wd) for t in tiles]
    assert all(r["skipped"] for r in again)
    h2 = _checkpoint(tmp_path / "m2.pt", 1)
    cfg2 = cfg.model_copy(update={"classify": cfg.classify.model_copy(update={"model": str(tmp_path / "m2.pt")})})
    third = [run_classify_tile(t, cfg2, wd) for t in tiles]
    assert all(not r["skipped"] and r["model_hash"] == h2 for r in third)


def test_a_missing_model_fails_the_tile_with_one_line(tiny_work, tmp_path):
    from tasks.classify import run_classify_tile

    cfg, wd = tiny_work
    cfg = cfg.model_copy(update={"classify": cfg.classify.model_copy(update={"enabled": True,
                                                                            "model": str(tmp_path / "none.pt")})})
    res = run_classify_tile(wd.live_tiles()[0], cfg, wd)
    assert res["status"] == "failed" and "none.pt" in res["error"] and "not found" in res["error"]
