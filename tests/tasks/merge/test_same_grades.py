"""Merge and repair act on the same grades: under ``repair.grades`` labels / model / all, the patches the
regions stage plans as bad are exactly the patches whose faces the merged mesh marks bad."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from storage.contracts.tile_mesh import GRADE_BAD, read_tile_mesh
from storage.patches.read import PatchStore
from storage.patches.write import write_side_table
from storage.workdir.layout import WorkDir, campus_frame, read_campus
from synth.corner_scene import write_campus_workdir
from tasks.config import CampusConfig
from tasks.merge import faces_in_tile, run_merge_tile
from tasks.regions import read_plan, run_regions


@pytest.fixture(scope="module")
def disagreeing(tmp_path_factory):
    """The corner scene with a grades table that contradicts its labels: every labelled-bad patch graded
    good, and every fifth labelled-good patch graded bad. Returns (work dir, {mode: bad keys})."""
    wd, _ = write_campus_workdir(tmp_path_factory.mktemp("grades") / "work")
    labelled, graded, every = [], [], []
    for t in wd.live_tiles():
        s = PatchStore(wd.tile_dir(t))
        keys = s.patches()["patch"]
        lab = s.side("labels")["label"]
        grade = np.where(lab == 1, 0, (np.arange(len(keys)) % 5 == 0)).astype(np.int8)
        write_side_table(wd.tile_dir(t), "grades", {"patch": keys, "score": grade.astype(np.float32),
                                                    "grade": grade}, s.meta)
        labelled.append(keys[lab == 1])
        graded.append(keys[grade == 1])
        every.append(keys)
    bad = {"labels": labelled, "model": graded, "all": every}
    return wd, {m: set(np.concatenate(k).tolist()) for m, k in bad.items()}


def _cfg(wd: WorkDir, mode: str) -> CampusConfig:
    cfg = CampusConfig.model_validate(read_campus(wd)["config"])
    cfg.repair.grades = mode
    cfg.repair.regions.min_patches, cfg.repair.regions.grow_cells = 1, 0
    return cfg


def _merged_bad(wd: WorkDir, cfg: CampusConfig) -> tuple[set, set]:
    """(keys of the patches holding a face the merged meshes mark bad, keys of every patch holding a face)."""
    origin = campus_frame(read_campus(wd)).origin_array
    bad, with_faces = set(), set()
    for t in wd.live_tiles():
        tm = read_tile_mesh(wd.tile_dir(t))
        own, keys = faces_in_tile(tm.vertices[tm.faces], cfg.grid(), origin, t)
        assert own.all()
        bad |= set(keys[tm.grade == GRADE_BAD].tolist())
        with_faces |= set(keys.tolist())
    return bad, with_faces


@pytest.mark.parametrize("mode", ["labels", "model", "all"])
def test_merge_marks_bad_exactly_the_patches_the_regions_plan(disagreeing, mode, tmp_path):
    src, truth = disagreeing
    shutil.copytree(src.root, tmp_path / "w")
    wd = WorkDir(tmp_path / "w")
    cfg = _cfg(wd, mode)
    plan = run_regions(cfg, wd)
    assert plan["status"] == "done"
    planned = set(np.concatenate([r.bad for r in read_plan(wd.root)]).tolist())
    assert planned == truth[mode] and truth["labels"] != truth["model"]
    results = [run_merge_tile(t, cfg, wd) for t in wd.live_tiles()]
    assert {r["grades_from"] for r in results} == {{"labels": "labels", "model": "grades", "all": "all"}[mode]}
    merged, with_faces = _merged_bad(wd, cfg)
    assert merged == planned & with_faces and merged


def test_a_new_grades_mode_merges_again(disagreeing, tmp_path):
    src, truth = disagreeing
    shutil.copytree(src.root, tmp_path / "w")
    wd = WorkDir(tmp_path / "w")
    first = [run_merge_tile(t, _cfg(wd, "labels"), wd) for t in wd.live_tiles()]
    assert _merged_bad(wd, _cfg(wd, "labels"))[0] <= truth["labels"]
    second = [run_merge_tile(t, _cfg(wd, "model"), wd) for t in wd.live_tiles()]
    assert not any(r["skipped"] for r in first + second)
    assert _merged_bad(wd, _cfg(wd, "model"))[0] <= truth["model"]
