"""The repair stages end to end on the synth 'tiny' campus: real images, cameras.json in the MLS frame."""

import json

import numpy as np
import pytest

from flows.campus import InlineExecutor, reprocess
from storage.workdir import WorkDir
from tasks.config import CampusConfig
from tasks.region_io import region_meshes_for_tile
from tasks.repair_stage import run_region, run_regions

pytestmark = pytest.mark.slow


def test_tiny_campus_regions_are_rebuilt_welded_and_textured(tiny_campus, tmp_path):
    cfg = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {"work_dir": str(tmp_path / "work"), "runner": "inline"})
    reprocess(cfg, InlineExecutor())
    wd = WorkDir(cfg.work_dir)
    plan = run_regions(cfg, wd)
    assert plan["n_regions"] > 0 and plan["grades"] == ["labels"]
    results = [run_region(k, cfg, wd) for k in plan["regions"]]
    assert all(r["status"] == "done" for r in results), [r.get("error") for r in results]
    rebuilt = [r for r in results if r["result"] == "rebuilt"]
    assert rebuilt and all(r["max_border_gap_m"] <= cfg.repair.mesh.stitch_tolerance_m for r in rebuilt)
    textured = 0
    for r in rebuilt:
        doc = json.loads((wd.root / "regions" / r["region"] / "region.json").read_text())
        textured += doc["texture"].get("seen_faces", 0)
        if doc["atlas"]:
            assert (wd.root / "regions" / r["region"] / "atlas.jpg").exists()
    assert textured > 0  # the vehicle images, moved through the registration, see rebuilt faces
    pieces = [m for t in wd.live_tiles() for m in region_meshes_for_tile(wd, t)]
    assert {m.region_id for m in pieces} == {r["region"] for r in rebuilt}
    for m in pieces:
        seen = np.isfinite(m.uv).all(axis=(1, 2))
        assert ((m.uv[seen] >= 0) & (m.uv[seen] <= 1)).all() and m.face_colors.shape == (len(m.faces), 3)
    # a second run skips every region
    assert all(run_region(k, cfg, wd)["skipped"] for k in plan["regions"])
