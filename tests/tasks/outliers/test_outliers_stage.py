"""The outliers stage reads the patches tables only: on a bucket it downloads no point or face store."""

from __future__ import annotations

import shutil

import numpy as np

from storage.patches.read import read_side_table
from storage.workdir.layout import WorkDir, read_campus
from synth.corner_scene import write_campus_workdir
from tasks.config import CampusConfig
from tasks.outliers.stage import run_outliers


def test_outliers_read_the_patches_tables_only(tmp_path):
    wd, _ = write_campus_workdir(tmp_path / "a" / "work")
    cfg = CampusConfig.model_validate(read_campus(wd)["config"])
    shutil.copytree(wd.root, tmp_path / "b")
    out_a = run_outliers(cfg, wd)
    other = WorkDir(tmp_path / "b")
    tiles = other.live_tiles()
    assert tiles
    for t in tiles:  # without the stores' points and faces: the same flags
        (other.tile_dir(t) / "points.parquet").unlink()
        (other.tile_dir(t) / "faces.parquet").unlink()
    out_b = run_outliers(cfg, other)
    assert out_a["n_patches"] == out_b["n_patches"] > 0
    for t in tiles:
        a = read_side_table(wd.tile_dir(t), "outliers")
        b = read_side_table(other.tile_dir(t), "outliers")
        assert a is not None and b is not None
        assert all(np.array_equal(a[0][c], b[0][c]) for c in a[0]) and a[1] == b[1]
