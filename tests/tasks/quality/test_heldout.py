"""Accuracy without truth: the held-out MLS strips (choice, absence from the repair's input), their figures
against the input mesh and the merged model, and the per-face scan-to-model distance and grader score in a
merged tile and its glb, per building too. Data built in code: one 10 m tile of a flat 8 x 4 m mesh with a
scan above it; one 50 m tile of a box building on a ground grid, scanned from the street (its facade and the
ground in front of it) and written into report.html."""

from __future__ import annotations

import numpy as np
import pytest

from storage.contracts.region_plan import Region
from storage.contracts.tile_mesh import read_tile_mesh, write_tile_mesh
from storage.frame import CampusFrame
from storage.ids import TileId
from storage.patches.schema import TileMeta
from storage.patches.write import write_side_table, write_tile_tables
from storage.workdir.layout import WorkDir, write_campus
from tasks.config import CampusConfig
from tasks.export.check import check_mesh_features, node_tools, validate_glbs
from tasks.export.gltf import GltfMesh, build_glb, glb_primitives, read_glb
from tasks.geometry.holdout import Holdout
from tasks.merge import run_merge_tile
from tasks.quality import ensure_heldout
from tasks.repair.region_io import read_region

ORIGIN = (500_000.0, 4_000_000.0, 0.0)
TILE = TileId(50000, 400000)
OFFSET_M = 0.03  # the scan lies this far above (in front of) the mesh
NX, NY, X0 = 8, 4, 1.0


def _plane() -> tuple[np.ndarray, np.ndarray]:
    ix, iy = np.meshgrid(np.arange(NX + 1), np.arange(NY + 1), indexing="xy")
    v = np.stack([ix.ravel() + X0, iy.ravel() + 1.0, np.full(ix.size, 0.5)], 1).astype(np.float32)
    f = [[j * (NX + 1) + i, j * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i + 1] for j in range(NY) for i in range(NX)]
    f += [[j * (NX + 1) + i, (j + 1) * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i] for j in range(NY) for i in range(NX)]
    return v, np.array(f)


def _scan(n_strips: int = 40, per_strip: int = 150) -> dict:
    """Two passes over the plane, ``OFFSET_M`` above it: each one-second strip covers a band of x."""
    rng = np.random.default_rng(0)
    t = np.repeat(np.arange(n_strips, dtype=np.float64), per_strip) + rng.random(n_strips * per_strip) * 0.99 + 1000
    x = X0 + ((t - 1000) % (n_strips / 2)) / (n_strips / 2) * NX  # pass 1 then pass 2 sweep the same x
    y = 1.0 + rng.random(len(t)) * NY
    z = np.full(len(t), 0.5 + OFFSET_M)
    return {"x": x.astype(np.float32), "y": y.astype(np.float32), "z": z.astype(np.float32), "gps_time": t}


def _cfg(work, share: float = 0.25, tile_size_m: float = 10.0) -> CampusConfig:
    return CampusConfig(work_dir=str(work), tiling={"tile_size_m": tile_size_m},
                        partition={"patch_size_m": (1.0, 1.0, 1.0)},
                        quality={"holdout_share": share, "holdout_block_s": 1.0, "holdout_seed": 5})


def _work_dir(cfg, tile: TileId, scan: dict, tri: np.ndarray) -> tuple[WorkDir, dict]:
    """A work dir with one tile store of ``tri``'s faces ((m, 3, 3) campus-local) and ``scan``, graded good with
    score 0.25 everywhere: (work dir, the store's points columns)."""
    from tasks.partition.kernels import build_tile_tables

    wd = WorkDir(cfg.work_dir)
    write_campus(wd, CampusFrame(origin=ORIGIN, crs="EPSG:32650"), {"matrix": np.eye(4).tolist(), "scale": 1.0},
                 cfg.model_dump(mode="json"), extra={"grid": cfg.grid().to_json()})
    tri = np.asarray(tri, np.float32)
    faces = {f"{a}{k}": tri[:, k, i] for k in range(3) for i, a in enumerate("xyz")}
    points, faces, patches = build_tile_tables(scan, faces, cfg.grid(), ORIGIN)
    meta = TileMeta(tile=tile.key, patch_size_m=(1.0, 1.0, 1.0), crs="EPSG:32650")
    write_tile_tables(wd.tile_dir(tile), points, faces, patches, meta)
    keys = patches["patch"]
    write_side_table(wd.tile_dir(tile), "grades", {"patch": keys, "score": np.full(len(keys), 0.25, np.float32),
                                                   "grade": np.zeros(len(keys), np.int8)}, meta)
    return wd, points


@pytest.fixture
def flat(tmp_path):
    """A work dir with one tile store (the plane's faces, the scan, grades with score 0.25 everywhere)."""
    cfg = _cfg(tmp_path / "work")
    v, f = _plane()
    wd, points = _work_dir(cfg, TILE, _scan(), v[f])
    return cfg, wd, points


def test_holdout_takes_whole_strips_deterministically_and_zero_turns_it_off():
    scan = _scan()
    xy = np.stack([scan["x"], scan["y"]], 1).astype(np.float64) + ORIGIN[:2]
    h = Holdout(share=0.25, block_s=1.0, seed=5)
    held = h.mask(scan["gps_time"], xy)
    strip = np.floor(scan["gps_time"]).astype(np.int64)
    held_strips = np.unique(strip[held])
    assert abs(len(held_strips) / 40 - 0.25) <= 0.05  # the share of the strips, to within a strip or two
    assert np.array_equal(held, np.isin(strip, held_strips))  # strips whole, never scattered points
    perm = np.random.default_rng(1).permutation(len(strip))
    assert np.array_equal(h.mask(scan["gps_time"][perm], xy[perm]), held[perm])  # order-free, repeatable
    assert not np.array_equal(Holdout(share=0.25, block_s=1.0, seed=6).mask(scan["gps_time"], xy), held)
    assert not Holdout(share=0.0).mask(scan["gps_time"], xy).any()
    # points without time: strips of ground cells
    cells = Holdout(share=0.5, cell_m=2.0, seed=1).mask(np.zeros(len(xy)), xy)
    cell = np.floor(xy / 2.0).astype(np.int64)
    for c in np.unique(cell, axis=0):
        inside = (cell == c).all(1)
        assert cells[inside].all() or not cells[inside].any()


def test_holdout_never_empties_a_patch_so_never_a_tile():
    t = np.full(20, 7.5)  # one strip only
    for seed in range(40):  # some seeds choose it: the patch then keeps it
        assert not Holdout(share=0.5, block_s=1.0, seed=seed).mask(t, np.zeros((20, 2)), np.zeros(20, np.int64)).any()
    two = np.r_[np.full(10, 7.5), np.full(10, 9.5)]
    patch = np.r_[np.zeros(10), np.ones(10)].astype(np.int64)
    for seed in range(40):
        m = Holdout(share=0.5, block_s=1.0, seed=seed).mask(two, np.zeros((20, 2)), patch)
        assert not m[:10].all() and not m[10:].all()


def test_held_out_points_are_absent_from_the_repair_input(flat):
    cfg, wd, points = flat
    keys = np.unique(points["patch"])
    region = Region("r0", 1, patches=keys[:20], bad=keys[:20], context=keys[20:], tiles=(TILE.key,))
    xy = np.stack([points["x"], points["y"]], 1).astype(np.float64) + ORIGIN[:2]
    held = cfg.quality.holdout().mask(points["gps_time"], xy, points["patch"])
    assert 0 < held.sum() < len(held)
    rr = read_region(region, cfg.grid(), wd.tile_dir, np.asarray(ORIGIN), cfg.quality.holdout())
    seen = np.concatenate([rr.input.mls_xyz, rr.input.ctx_xyz])
    assert rr.held_out == held.sum() and len(seen) == len(held) - held.sum()
    kept_t = {tuple(p) for p in np.stack([points["x"], points["y"]], 1)[~held].tolist()}
    assert {tuple(p) for p in seen[:, :2].astype(np.float32).tolist()} <= kept_t
    everything = read_region(region, cfg.grid(), wd.tile_dir, np.asarray(ORIGIN), Holdout(share=0.0))
    assert everything.held_out == 0 and len(everything.input.mls_xyz) + len(everything.input.ctx_xyz) == len(held)


def test_held_out_figures_give_the_known_offset(flat):
    cfg, wd, _ = flat
    tm = _merged(cfg, wd)
    lifted = type(tm)(**{**tm.__dict__, "vertices": tm.vertices + np.float32([0, 0, 0.01])})
    write_tile_mesh(wd.tile_dir(TILE), lifted)  # the merged model 1 cm nearer the scan than the input mesh
    doc = ensure_heldout(cfg, wd)
    assert 0 < doc["held_out"] < doc["points"]
    inp, merged = doc["campus"]["input mesh"], doc["campus"]["merged model"]
    assert inp["points"] == merged["points"] == doc["held_out"]
    assert inp["median_m"] == pytest.approx(OFFSET_M, abs=2e-4) and merged["median_m"] == pytest.approx(0.02, abs=2e-4)
    assert inp["within_5cm"] == 1.0 and inp["within_10cm"] == 1.0
    assert doc["tiles"][TILE.key]["merged model"] == merged  # one tile: its figures are the campus's
    assert ensure_heldout(cfg, wd) == doc  # cached
    assert ensure_heldout(_cfg(cfg.work_dir, share=0.0), wd) == {"status": "off"}


def _merged(cfg, wd):
    assert run_merge_tile(TILE, cfg, wd)["status"] == "done"
    return read_tile_mesh(wd.tile_dir(TILE))


def test_merged_faces_carry_scan_distance_and_score_into_a_valid_glb(flat, tmp_path):
    cfg, wd, _ = flat
    tm = _merged(cfg, wd)
    seen = np.isfinite(tm.face_deviation)
    assert seen.mean() > 0.9  # the scan covers the plane
    assert np.allclose(tm.face_deviation[seen], OFFSET_M, atol=1e-4)  # positive: the scan in front (+z normals)
    assert np.allclose(tm.face_score, 0.25)
    faces = tm.faces
    mesh = GltfMesh(positions=tm.vertices, faces=faces, feature=np.zeros(len(faces), np.int64),
                    grade=np.zeros(1, np.int8), source=np.zeros(1, np.int8), region=np.full(1, -1, np.int32),
                    face_texture=np.full(len(faces), -1, np.int16), face_deviation=tm.face_deviation,
                    face_confidence=tm.face_score)
    data = build_glb(mesh)
    doc, binary = read_glb(data)
    meta = doc["extensions"]["EXT_structural_metadata"]
    table = meta["propertyTables"][1]
    assert table["class"] == "face_quality" and table["count"] == len(faces)
    assert meta["schema"]["classes"]["face_quality"]["properties"]["deviation_m"]["componentType"] == "FLOAT32"
    values = {k: np.frombuffer(binary, np.float32, len(faces), doc["bufferViews"][p["values"]]["byteOffset"])
              for k, p in table["properties"].items()}
    (prim,) = glb_primitives(data)
    fid1 = prim["_FEATURE_ID_1"][prim["indices"]]
    assert (fid1 == fid1[:, :1]).all()  # one feature per face
    np.testing.assert_array_equal(values["deviation_m"][fid1[:, 0]], tm.face_deviation)
    np.testing.assert_array_equal(values["confidence"][fid1[:, 0]], tm.face_score)
    assert check_mesh_features(data) == []
    node, reason = node_tools()
    if node is None:
        pytest.fail(reason)
    (tmp_path / "q.glb").write_bytes(data)
    (report,) = validate_glbs([tmp_path / "q.glb"])
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]


# ------------------------------------------------------------------------------ per building

BOX = (10.0, 10.0, 20.0, 18.0, 12.0)  # x0, y0, x1, y1, height (campus-local metres): one 10 x 8 m building
FACADE_OFFSET_M = 0.05  # the facade's scan lies this far in front of it; the ground's OFFSET_M above it
BOX_TILE = TileId(10000, 80000)  # 50 m tiles: the campus origin's


def _quads(corner, u, v, nu: int, nv: int) -> np.ndarray:
    """(2 nu nv, 3, 3) triangles of the parallelogram ``corner + [0, 1] u + [0, 1] v`` in nu x nv quads."""
    a, b = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    p = np.asarray(corner, float) + (a.ravel()[:, None] * np.asarray(u) / nu) + (b.ravel()[:, None] * np.asarray(v) / nv)
    du, dv = np.asarray(u) / nu, np.asarray(v) / nv
    return np.concatenate([np.stack([p, p + du, p + du + dv], 1), np.stack([p, p + du + dv, p + dv], 1)])


def _box_scene() -> np.ndarray:
    """A 40 x 30 m ground grid at z 0 (none under the box) and the box's four walls and roof, 1 m faces."""
    x0, y0, x1, y1, h = BOX
    ground = _quads((0, 0, 0), (40, 0, 0), (0, 30, 0), 40, 30)
    c = ground.mean(1)
    ground = ground[~((c[:, 0] > x0) & (c[:, 0] < x1) & (c[:, 1] > y0) & (c[:, 1] < y1))]
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    walls = [_quads((*a, 0), (b[0] - a[0], b[1] - a[1], 0), (0, 0, h), int(np.hypot(b[0] - a[0], b[1] - a[1])), int(h))
             for a, b in zip(corners, corners[1:] + corners[:1])]
    roof = _quads((x0, y0, h), (x1 - x0, 0, 0), (0, y1 - y0, 0), int(x1 - x0), int(y1 - y0))
    return np.concatenate([ground, *walls, roof])


def _street_scan(per_strip: int = 300) -> dict:
    """Two passes along the street south of the box (40 one-second strips, each 2 m of x): in each strip, half
    the points on the box's south facade ``FACADE_OFFSET_M`` in front of it (where the strip passes it), the
    rest on the ground ``OFFSET_M`` above it, 2 to 8 m from the facade."""
    x0, y0, x1, _, h = BOX
    rng = np.random.default_rng(3)
    t = np.repeat(np.arange(40, dtype=np.float64), per_strip) + rng.random(40 * per_strip) * 0.99 + 1000
    x = ((t - 1000) % 20) * 2.0
    facade = (rng.random(len(t)) < 0.5) & (x >= x0 + 0.1) & (x <= x1 - 0.1)
    y = np.where(facade, y0 - FACADE_OFFSET_M, y0 - 2.0 - rng.random(len(t)) * 6.0)
    z = np.where(facade, 0.5 + rng.random(len(t)) * (h - 1.0), OFFSET_M)
    return {"x": x.astype(np.float32), "y": y.astype(np.float32), "z": z.astype(np.float32), "gps_time": t}


def test_held_out_figures_per_building_and_in_the_report(tmp_path):
    from tasks.report import run_report

    cfg = _cfg(tmp_path / "work", tile_size_m=50.0)
    wd, _ = _work_dir(cfg, BOX_TILE, _street_scan(), _box_scene())
    assert run_merge_tile(BOX_TILE, cfg, wd)["status"] == "done"
    doc = ensure_heldout(cfg, wd)
    assert doc["footprints"]["buildings"] == 1
    (box,) = [b for b in doc["buildings"] if b["id"]]
    other = doc["buildings"][-1]
    assert other["id"] == 0 and other["name"] == "other"
    assert box["id"] == 1 and box["area_m2"] == pytest.approx(80.0, rel=0.15)
    assert box["height_m"] == pytest.approx(12.0, abs=0.5)
    assert box["centroid"] == pytest.approx([15.0, 14.0], abs=0.6)
    assert box["centroid_world"] == pytest.approx([ORIGIN[0] + box["centroid"][0], ORIGIN[1] + box["centroid"][1]])
    for model in ("input mesh", "merged model"):
        on, off = box["models"][model], other["models"][model]
        assert on["points"] > 0 and off["points"] > 0
        assert on["points"] + off["points"] == doc["campus"][model]["points"] == doc["held_out"]
        assert on["median_m"] == pytest.approx(FACADE_OFFSET_M, abs=2e-4)  # the facade's points, on the building
        assert off["median_m"] == pytest.approx(OFFSET_M, abs=2e-4)  # the ground's, on none
    assert doc["tiles"][BOX_TILE.key] == doc["campus"]  # the tile and campus figures as before
    assert ensure_heldout(cfg, wd) == doc  # cached

    run_report(cfg, wd, quality=False)
    html = wd.report_html.read_text()
    section = html[html.index("Accuracy without truth: held-out MLS strips</h2>"):]
    assert "<h3>Per building</h3>" in section and section.index("<h3>Per building</h3>") < section.index("Per tile")
    assert "<th>footprint (m²)</th>" in section and "<td>other (no building)</td>" in section
    assert f"<tr><td>1</td><td>{box['area_m2']:,.0f}</td><td>{box['height_m']:.1f}</td>" \
           f"<td>{box['models']['input mesh']['points']:,}</td>" in section


def test_grouped_sums_add_up_to_each_groups_dense_sums_across_tiles():
    from tasks.quality.buildings import GroupedSums
    from tasks.quality.heldout import HeldOutSums

    rng = np.random.default_rng(4)
    g = rng.integers(0, 6, 3000)
    d = np.where(rng.random(3000) < 0.05, np.inf, rng.exponential(0.05, 3000))
    tiles = np.array_split(rng.permutation(3000), 3)  # a building's points in several tiles
    s = GroupedSums.merge([GroupedSums.of(g[i], d[i]) for i in tiles])
    assert s.groups().tolist() == sorted(set(g.tolist()))
    for b in range(6):
        np.testing.assert_array_equal(s.sums(b).counts, HeldOutSums.of(d[g == b]).counts)
    assert sum(s.sums(b).n for b in range(6)) == 3000 and s.sums(9).n == 0
    assert len(s.keys) <= 3000  # sparse: never more pairs than points
