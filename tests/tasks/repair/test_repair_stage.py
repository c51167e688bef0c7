"""The repair stages on a hand-made work dir: a region across a tile corner, stitching, resume, grades."""

import json

import numpy as np
import pytest

from storage.contracts.region_mesh import region_meshes_for_tile
from storage.ids import TileId
from storage.patches.read import PatchStore
from storage.patches.state import patch_grades
from storage.patches.write import write_side_table
from storage.workdir.layout import campus_frame, read_campus
from synth.corner_scene import CENTRE, HALF, building_mesh, write_campus_workdir
from tasks.config import CampusConfig
from tasks.merge import faces_in_tile
from tasks.regions import read_plan, run_regions
from tasks.repair import run_region
from tasks.repair.chart import boundary_edges

TILES = ["0_0", "0_1", "1_0", "1_1"]


def _cfg(wd):
    cfg = CampusConfig.model_validate(read_campus(wd)["config"])
    cfg.repair.texture.enabled = False
    cfg.repair.fusion.mls_spacing_m = 0.05
    return cfg


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    wd, bad = write_campus_workdir(tmp_path_factory.mktemp("corner") / "work")
    cfg = _cfg(wd)
    plan = run_regions(cfg, wd)
    results = [run_region(k, cfg, wd) for k in plan["regions"]]
    return wd, cfg, bad, plan, results


def _tile_faces(wd, tile):
    s = PatchStore(wd.tile_dir(TileId.from_key(tile)))
    _, f = s.read_all(point_columns=["x"], face_columns=[*(f"{a}{v}" for v in range(3) for a in "xyz"),
                                                          "vid0", "vid1", "vid2"])
    tri = np.stack([np.stack([f[f"{a}{v}"] for a in "xyz"], 1) for v in range(3)], 1).astype(np.float64)
    return tri, np.stack([f[f"vid{v}"] for v in range(3)], 1)


def _assemble(wd):
    """Every tile's faces minus those the regions replace, plus every rebuilt region once, welded by id."""
    tris, vids, regions = [], [], {}
    for t in TILES:
        tri, vid = _tile_faces(wd, t)
        keep = np.ones(len(tri), bool)
        for rm in region_meshes_for_tile(wd.root, TileId.from_key(t)):
            keep[rm.replaced_rows] = False
            regions[rm.region_id] = rm
        tris.append(tri[keep])
        vids.append(vid[keep])
    for rm in regions.values():
        tris.append(rm.vertices[rm.faces].astype(np.float64))
        vids.append(np.where(rm.vertex_ids >= 0, rm.vertex_ids, rm.vertex_ids - (1 << 40))[rm.faces])
    tri, vid = np.concatenate(tris), np.concatenate(vids)
    _uid, first, inv = np.unique(vid.ravel(), return_index=True, return_inverse=True)
    return tri.reshape(-1, 3)[first], inv.reshape(-1, 3)


def test_region_spanning_a_tile_corner_is_repaired_as_one_piece(corner):
    wd, cfg, bad, plan, results = corner
    assert plan["status"] == "done" and plan["n_regions"] == 1 and plan["n_bad"] == len(bad)
    assert plan["weights"] == [float(read_plan(wd.root)[0].est_bytes)] and plan["weights"][0] > 1
    (r,) = results
    assert r["status"] == "done" and r["result"] == "rebuilt" and sorted(r["tiles"]) == TILES
    pieces = {t: region_meshes_for_tile(wd.root, TileId.from_key(t)) for t in TILES}
    assert all(len(p) == 1 and p[0].region_id == plan["regions"][0] for p in pieces.values())
    assert all(len(p[0].faces) == r["rebuilt_faces"] for p in pieces.values())  # each tile gets the whole region
    # and the merge's rule hands each rebuilt face to exactly one tile
    origin = campus_frame(read_campus(wd)).origin_array
    owned = [faces_in_tile(p[0].vertices[p[0].faces], cfg.grid(), origin, TileId.from_key(t))[0]
             for t, p in pieces.items()]
    assert (np.sum(owned, axis=0) == 1).all()
    assert sum(len(p[0].replaced_rows) for p in pieces.values()) == r["replaced_faces"]
    assert 0.5 * r["zone_faces"] < r["replaced_faces"] <= r["zone_faces"]  # zone faces the scan agrees with stay
    # the protrusion is cut back: new vertices lie on the true walls (a 4 x 4 m box around CENTRE)
    one = pieces[TILES[0]][0]
    v = one.vertices[one.vertex_ids < 0].astype(np.float64)
    wall = np.abs(np.abs(v[:, :2] - CENTRE).max(1) - HALF)
    assert len(v) > 1000 and np.percentile(wall, 99) < 0.02


def test_stitched_output_has_no_border_gap(corner):
    wd, cfg, _, _, results = corner
    assert results[0]["max_border_gap_m"] <= cfg.repair.mesh.stitch_tolerance_m
    v0, f0, _ = building_mesh()
    v, f = _assemble(wd)
    # welded by vertex id: the only open edges left are the original mesh's outer rim
    assert len(boundary_edges(f, len(v))) == len(boundary_edges(f0, len(v0)))
    e = v[boundary_edges(f, len(v))]
    assert np.abs(e[..., :2] - CENTRE).max() > HALF + 3.0  # that rim is the ground ring's outside


def test_region_is_redone_when_grades_or_parameters_change(corner, tmp_path):
    import shutil

    wd0 = corner[0]
    shutil.copytree(wd0.root, tmp_path / "w", symlinks=True)
    from storage.workdir.layout import WorkDir

    wd = WorkDir(tmp_path / "w")
    cfg = _cfg(wd)
    key = run_regions(cfg, wd)["regions"][0]
    assert run_region(key, cfg, wd)["skipped"]
    cfg.repair.fusion.smoothness = 0.7
    assert not run_region(key, cfg, wd)["skipped"]
    assert run_region(key, cfg, wd)["skipped"]
    # one more bad patch next to the region: the plan and the region change, the region is redone
    td = wd.tile_dir(TileId.from_key("0_0"))
    s = PatchStore(td)
    lab = s.side("labels")["label"].copy()
    ring = run_regions(cfg, wd)
    plan = json.loads((wd.root / "regions" / "regions.json").read_text())["regions"][0]
    extra = np.flatnonzero(np.isin(s.patches()["patch"], plan["context"]) & (lab == 0))[0]
    lab[extra] = 1
    write_side_table(td, "labels", {"patch": s.patches()["patch"], "label": lab}, s.meta)
    ring = run_regions(cfg, wd)
    assert ring["n_bad"] == corner[3]["n_bad"] + 1
    r = run_region(ring["regions"][0], cfg, wd)
    assert r["status"] == "done" and not r["skipped"]


def test_grades_are_preferred_to_labels(corner, tmp_path):
    import shutil

    shutil.copytree(corner[0].root / "tiles" / "0_0", tmp_path / "t")
    s = PatchStore(tmp_path / "t")
    keys, g, src = patch_grades(s, "auto")
    assert src == "labels" and g.sum() > 0
    write_side_table(tmp_path / "t", "grades", {"patch": keys, "score": np.zeros(len(keys), np.float32),
                                                "grade": np.zeros(len(keys), np.int8)}, s.meta)
    s = PatchStore(tmp_path / "t")
    assert patch_grades(s, "auto")[2] == "grades" and patch_grades(s, "auto")[1].sum() == 0
    assert patch_grades(s, "labels")[1].sum() == g.sum()
    keys_all, g_all, src_all = patch_grades(s, "all")  # fusion everywhere
    assert src_all == "all" and np.array_equal(keys_all, keys) and (g_all == 1).all()
