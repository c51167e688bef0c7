"""The classify stage on the tiny synth campus: grades for every pair, unknown for the rest, resumable."""

from __future__ import annotations

import numpy as np
import torch

from ms3d_model.profiles import PROFILES
from ms3d_model.train import make_model, save_checkpoint
from storage.patches.read import PatchStore


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


def test_the_users_labels_win_and_regrade_only_their_tile(tiny_work, tmp_path):
    """A patch the user marked in the viewer takes the user's grade whatever the model says (both ways);
    only the tile holding the labels grades again; a broken labels file fails that tile in one line."""
    import shutil

    from storage.grid import PatchGrid
    from storage.workdir.user_labels import LABELS_DIR, append_user_label
    from tasks.classify import run_classify_tile

    cfg, wd = tiny_work
    _checkpoint(tmp_path / "u.pt", 0)
    cfg = cfg.model_copy(update={"classify": cfg.classify.model_copy(update={"enabled": True, "model": str(tmp_path / "u.pt"),
                                                                             "evidence": False})})
    tiles = wd.live_tiles()
    try:
        [run_classify_tile(t, cfg, wd) for t in tiles]
        graded = [t for t in tiles if (PatchStore(wd.tile_dir(t)).side("grades")["grade"] >= 0).any()]
        t0 = graded[0]
        tiles = [t0] + [t for t in tiles if t != t0]
        store = PatchStore(wd.tile_dir(t0))
        keys, grade = store.patches()["patch"], store.side("grades")["grade"]
        good, bad = keys[grade == 0][:1], keys[grade == 1][:1]
        flip = np.concatenate([good, bad])
        assert len(flip) >= 1
        for key, lab in zip(flip, [1] * len(good) + [0] * len(bad)):
            append_user_label(wd.root, tuple(int(v) for v in PatchGrid.unpack(np.array([key]))[0]), lab)
        res = [run_classify_tile(t, cfg, wd) for t in tiles]
        assert not res[0]["skipped"] and res[0]["n_user_labels"] == len(flip)
        assert all(r["skipped"] for r in res[1:])
        g2 = dict(zip(keys.tolist(), PatchStore(wd.tile_dir(t0)).side("grades")["grade"].tolist()))
        assert [g2[int(k)] for k in good] == [1] * len(good) and [g2[int(k)] for k in bad] == [0] * len(bad)
        assert sum(g2[int(k)] != int(g) for k, g in zip(keys, grade)) == len(flip)  # nothing else moved
        assert run_classify_tile(t0, cfg, wd)["skipped"]
        (wd.root / LABELS_DIR / "broken.csv").write_text("i,j,k,label,time\n1,2,3,7,now\n")
        failed = run_classify_tile(t0, cfg, wd)
        assert failed["status"] == "failed" and "broken.csv" in failed["error"] and "label must be" in failed["error"]
    finally:
        shutil.rmtree(wd.root / LABELS_DIR, ignore_errors=True)


def test_count_outliers_are_graded_unknown_when_asked_and_the_record_says_so(tiny_work, tmp_path):
    """classify.outliers 'unknown': the patches the outliers stage flagged by count get grade -1 (their score
    kept), the grades' metadata and the unit record count them; 'grade' (the default) grades them."""
    import json
    import shutil

    import pyarrow.parquet as pq

    from storage.workdir.layout import WorkDir
    from tasks.classify import run_classify_tile

    cfg, wd = tiny_work
    shutil.copytree(wd.root, tmp_path / "work")
    wd = WorkDir(tmp_path / "work")
    _checkpoint(tmp_path / "m.pt", 0)
    base = cfg.classify.model_copy(update={"enabled": True, "model": str(tmp_path / "m.pt"), "evidence": False})
    cfg_grade = cfg.model_copy(update={"work_dir": str(wd.root), "classify": base})
    cfg_unk = cfg.model_copy(update={"work_dir": str(wd.root), "classify": base.model_copy(update={"outliers": "unknown"})})
    n_flagged = 0
    for t in wd.live_tiles():
        store = PatchStore(wd.tile_dir(t))
        o = store.side("outliers")
        flagged = o["outlier_points"] | o["outlier_faces"]
        run_classify_tile(t, cfg_grade, wd)
        graded = store.side("grades")["grade"]
        res = run_classify_tile(t, cfg_unk, wd)
        assert not res["skipped"]  # the switch regrades
        g = store.side("grades")
        pair = graded >= 0
        assert (g["grade"][flagged] == -1).all()
        np.testing.assert_array_equal(g["grade"][~flagged], graded[~flagged])
        assert res["n_outlier_unknown"] == int((flagged & pair).sum() + (flagged & ~pair).sum())
        meta = json.loads(pq.read_schema(wd.tile_dir(t) / "grades.parquet").metadata[b"ms3d"])
        assert meta["outliers"] == "unknown" and meta["outliers_unknown"] == res["n_outlier_unknown"]
        n_flagged += int((flagged & pair).sum())
    assert n_flagged > 0
