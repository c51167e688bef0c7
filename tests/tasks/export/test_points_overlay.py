"""The MLS points overlay: thinned registered points as a POINTS tileset in the mesh tiles' frame."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from storage.patches.read import PatchStore
from storage.patches.write import write_side_table
from storage.workdir.layout import campus_frame, read_campus
from synth.corner_scene import write_campus_workdir
from tasks.export.check import check_tileset, node_tools, validate_glbs
from tasks.export.georef import EnuProjector, gltf_to_enu, make_georef
from tasks.export.gltf import glb_primitives, srgb_to_linear_u8
from tasks.export.points import STATUS_COLOURS
from tasks.export.stage import write_points_overlay


@pytest.fixture
def corner(tmp_path):
    wd, bad = write_campus_workdir(tmp_path / "work")
    frame = campus_frame(read_campus(wd))
    georef = make_georef(frame.crs, frame.origin, (10.0, 10.0, 0.0))
    return wd, bad, georef, [t.key for t in wd.live_tiles()]


def _overlay_points(out):
    """(ECEF (n, 3) float64 through the tileset's transform, colours (n, 4) uint8) of every content."""
    doc = json.loads((out / "tileset.json").read_text())
    m = np.asarray(doc["root"]["transform"], np.float64).reshape(4, 4).T
    pos, col = [], []
    for child in doc["root"]["children"]:
        (prim,) = glb_primitives((out / child["content"]["uri"]).read_bytes())
        assert "indices" not in prim
        pos.append(gltf_to_enu(prim["POSITION"]) @ m[:3, :3].T + m[:3, 3])
        col.append(prim["COLOR_0"])
    return np.concatenate(pos), np.concatenate(col)


def test_overlay_holds_every_point_in_the_mesh_frame_coloured_by_grade(corner):
    wd, _, georef, tiles = corner
    out = wd.root / "output" / "points"
    res = write_points_overlay(wd.root / "tiles", out, tiles, georef)
    stores = [PatchStore(wd.tile_dir(t)) for t in wd.live_tiles()]
    n = sum(s.n_points for s in stores)
    assert res["written"] and res["tiles"] == len(tiles) and res["points"] == n  # below the budget: all
    assert check_tileset(out) == []
    ecef, colours = _overlay_points(out)
    xyz = np.concatenate([np.stack([s.read_all(["x", "y", "z"], ["x0"])[0][c] for c in "xyz"], axis=1) for s in stores])
    direct = EnuProjector(georef).local_to_ecef(xyz)
    assert cKDTree(direct).query(ecef)[0].max() < 1e-3  # the same ECEF positions as the mesh tiles' frame
    # colour: labelled-bad patches red, labelled-good green (the labels stand in for grades here)
    n_bad = sum(int(s.patches()["n_points"][s.side("labels")["label"] == 1].sum()) for s in stores)
    red, green = (srgb_to_linear_u8(STATUS_COLOURS[[k]])[0] for k in (1, 0))
    assert n_bad > 0 and (colours == red).all(axis=1).sum() == n_bad
    assert (colours == green).all(axis=1).sum() == n - n_bad


def test_overlay_is_thinned_to_the_budget_and_rewritten_only_when_grades_change(corner):
    wd, _, georef, tiles = corner
    out = wd.root / "output" / "points"
    res = write_points_overlay(wd.root / "tiles", out, tiles, georef, budget=2000)
    assert abs(res["points"] - 2000) <= len(tiles)
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    again = write_points_overlay(wd.root / "tiles", out, tiles, georef, budget=2000)
    assert not again["written"] and again["points"] == res["points"]
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    t = wd.live_tiles()[0]
    s = PatchStore(wd.tile_dir(t))
    keys = s.patches()["patch"]
    write_side_table(wd.tile_dir(t), "grades", {"patch": keys, "score": np.full(len(keys), 0.9, np.float32),
                                                "grade": np.ones(len(keys), np.int8)}, s.meta)
    third = write_points_overlay(wd.root / "tiles", out, tiles, georef, budget=2000)
    assert third["written"] and third["points"] == res["points"]


def test_overlay_colours_by_the_grades_repair_acted_on(corner):
    """Grades that contradict the labels: the overlay follows ``repair.grades`` (one rule with regions and
    merge), so "labels" shows the labels and "model" the grades."""
    wd, _, georef, tiles = corner
    stores = [PatchStore(wd.tile_dir(t)) for t in wd.live_tiles()]
    for t, s in zip(wd.live_tiles(), stores):
        keys = s.patches()["patch"]
        write_side_table(wd.tile_dir(t), "grades", {"patch": keys, "score": np.full(len(keys), 0.9, np.float32),
                                                    "grade": np.ones(len(keys), np.int8)}, s.meta)
    n = sum(s.n_points for s in stores)
    n_bad_labels = sum(int(s.patches()["n_points"][s.side("labels")["label"] == 1].sum()) for s in stores)
    red = srgb_to_linear_u8(STATUS_COLOURS[[1]])[0]
    out = wd.root / "output" / "points"
    for mode, n_red in (("labels", n_bad_labels), ("model", n)):
        res = write_points_overlay(wd.root / "tiles", out, tiles, georef, grades_mode=mode)
        assert res["written"]  # a mode switch rewrites the overlay
        assert (_overlay_points(out)[1] == red).all(axis=1).sum() == n_red
    assert 0 < n_bad_labels < n


def test_points_glbs_pass_the_gltf_validator(corner):
    node, reason = node_tools()
    if node is None:
        pytest.fail(reason)
    wd, _, georef, tiles = corner
    out = wd.root / "output" / "points"
    write_points_overlay(wd.root / "tiles", out, tiles, georef, budget=5000)
    reports = validate_glbs(sorted(out.glob("*.glb")))
    assert len(reports) == len(tiles)
    assert all(r["errors"] == 0 and r["warnings"] == 0 for r in reports), [r["messages"] for r in reports]


def test_no_store_no_overlay(corner, tmp_path):
    _, _, georef, tiles = corner
    out = tmp_path / "points"
    out.mkdir()
    (out / "old.glb").write_bytes(b"x")
    assert write_points_overlay(tmp_path / "nowhere", out, tiles, georef)["tiles"] == 0
    assert not out.exists()
