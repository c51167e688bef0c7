"""The region plan reads the patches and side tables only: on a bucket it downloads no point or face store."""

from __future__ import annotations

import shutil

from storage.workdir.layout import WorkDir, read_campus
from synth.corner_scene import write_campus_workdir
from tasks.config import CampusConfig
from tasks.regions import run_regions


def test_the_region_plan_reads_no_point_or_face_store(tmp_path):
    wd, bad = write_campus_workdir(tmp_path / "a" / "work")
    cfg = CampusConfig.model_validate(read_campus(wd)["config"])
    shutil.copytree(wd.root, tmp_path / "b")
    other = WorkDir(tmp_path / "b")
    for t in other.live_tiles():
        (other.tile_dir(t) / "points.parquet").unlink()
        (other.tile_dir(t) / "faces.parquet").unlink()
    a, b = run_regions(cfg, wd), run_regions(cfg, other)
    assert a["status"] == b["status"] == "done" and a["n_bad"] == len(bad) > 0
    assert (a["regions"], a["weights"]) == (b["regions"], b["weights"])
