"""The repair stages end to end in the campus flow on the synth 'tiny' campus: the shipped model grades
the pairs, the regions are rebuilt, textured from the real images (cameras.json in the MLS frame) and
merged into the tiles' meshes."""

import json

import numpy as np
import pytest

from flows.campus import InlineExecutor, run_campus
from storage.contracts.region_mesh import region_meshes_for_tile
from storage.contracts.tile_mesh import SOURCE_REBUILT, read_tile_mesh
from storage.workdir.layout import WorkDir
from tasks.config import CampusConfig
from tasks.regions import read_plan
from tasks.repair import run_region

pytestmark = pytest.mark.slow


def test_tiny_campus_regions_are_rebuilt_welded_textured_and_merged(tiny_campus, tmp_path):
    cfg = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {"work_dir": str(tmp_path / "work"), "runner": "inline"})
    summary = run_campus(cfg, executor=InlineExecutor())
    wd = WorkDir(cfg.work_dir)
    plan = json.loads((wd.root / "regions" / "regions.json").read_text())
    assert set(plan["grades"].values()) == {"grades"}  # the classify stage's grades, not the labels
    keys = [r.key for r in read_plan(wd.root)]
    assert keys and summary["stages"]["repair"]["run"] == len(keys)
    results = [json.loads((wd.root / "regions" / k / "region.json").read_text())["summary"] for k in keys]
    rebuilt = [r for r in results if r["result"] == "rebuilt"]
    assert rebuilt and all(r["max_border_gap_m"] <= cfg.repair.mesh.stitch_tolerance_m for r in rebuilt)
    textured = 0
    for r in rebuilt:
        doc = json.loads((wd.root / "regions" / r["region"] / "region.json").read_text())
        textured += doc["texture"].get("seen_faces", 0)
        if doc["atlas"]:
            assert (wd.root / "regions" / r["region"] / "atlas.jpg").exists()
    assert textured > 0  # the vehicle images, moved through the registration, see rebuilt faces
    pieces = list({m.region_id: m for t in wd.live_tiles() for m in region_meshes_for_tile(wd.root, t)}.values())
    assert {m.region_id for m in pieces} == {r["region"] for r in rebuilt}
    for m in pieces:
        seen = np.isfinite(m.corner_uv).all(axis=(1, 2))
        assert ((m.corner_uv[seen] >= 0) & (m.corner_uv[seen] <= 1)).all() and m.face_colors.shape == (len(m.faces), 3)
    # the merge took the rebuilt faces: every piece's faces are in its tile's merged mesh
    merged_rebuilt = sum(int((read_tile_mesh(wd.tile_dir(t)).source == SOURCE_REBUILT).sum()) for t in wd.live_tiles()
                         if (wd.tile_dir(t) / "merged.npz").exists())
    assert merged_rebuilt >= 0.99 * sum(len(m.faces) for m in pieces) > 0
    # a second run skips every region
    assert all(run_region(k, cfg, wd)["skipped"] for k in keys)
    again = run_campus(cfg, executor=InlineExecutor())
    assert again["stages"]["repair"]["run"] == 0 and again["stages"]["repair"]["skipped"] == len(keys)
