"""Merge: a hand-made two-tile store with a rebuilt region across the tile border, and the tiny synth
campus merged and exported through the export checks."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from storage.contracts.tile_mesh import GRADE_BAD, GRADE_GOOD, SOURCE_MESH, SOURCE_REBUILT, read_tile_mesh
from storage.frame import CampusFrame
from storage.ids import TileId
from storage.patches.schema import TileMeta
from storage.patches.write import write_side_table, write_tile_tables
from storage.workdir.layout import WorkDir, campus_frame, read_campus, write_campus
from tasks.config import CampusConfig
from tasks.merge import FaceSoup, RegionMesh, run_merge_tile, weld_soup
from tasks.merge.weld import face_keep_mask, weld_corners, weld_keys
from tasks.partition.kernels import build_tile_tables

ORIGIN = (500_000.0, 4_000_000.0, 0.0)
SOURCE = 7
NX, NY = 8, 4  # unit squares over local x in [6, 14], y in [0, 4]: tiles 50000 (x < 10) and 50001
X0 = 6.0
Z = 0.5
REGION = 3
REPLACED_CELLS = [(9, 1), (9, 2), (10, 1), (10, 2)]  # world cells (i - 50000, j - 4000000): 2 x 2 m across x = 10
TILES = (TileId(50000, 400000), TileId(50001, 400000))


def _vid(ix: int, iy: int) -> int:
    return (SOURCE << 32) | (iy * (NX + 1) + ix)


def _grid_mesh():
    """(vertices (n, 3) float32 local, faces (m, 3), vertex ids (n,)) of the NX x NY unit-square grid."""
    ix, iy = np.meshgrid(np.arange(NX + 1), np.arange(NY + 1), indexing="xy")
    v = np.stack([ix.ravel() + X0, iy.ravel(), np.full(ix.size, Z)], axis=1).astype(np.float32)
    faces = []
    for j in range(NY):
        for i in range(NX):
            a, b, c, d = j * (NX + 1) + i, j * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i + 1, (j + 1) * (NX + 1) + i
            faces += [[a, b, c], [a, c, d]]
    return v, np.array(faces), (np.int64(SOURCE) << 32) | np.arange(len(v), dtype=np.int64)


def _cfg(work: Path) -> CampusConfig:
    return CampusConfig(work_dir=str(work), tiling={"tile_size_m": 10.0}, partition={"patch_size_m": (1.0, 1.0, 1.0)})


def _cell_key(cfg, i: int, j: int) -> int:
    """Packed key of the patch over local x in [i, i + 1), y in [j, j + 1) (1 m patches, integer origin)."""
    return int(cfg.grid().pack(np.array([[int(ORIGIN[0]) + i, int(ORIGIN[1]) + j, 0]]))[0])


@pytest.fixture
def handmade(tmp_path):
    """A work dir with two tile stores of one textured 8 x 4 m grid mesh; patches 1 x 1 x 1 m, tiles 10 m;
    labels mark the four replaced cells bad and one more cell (13, 0) bad."""
    work = tmp_path / "work"
    cfg = _cfg(work)
    wd = WorkDir(work)
    frame = CampusFrame(origin=ORIGIN, crs="EPSG:32650")
    write_campus(wd, frame, {"matrix": np.eye(4).tolist(), "scale": 1.0}, cfg.model_dump(mode="json"),
                 extra={"grid": cfg.grid().to_json()})
    atlas = tmp_path / "mesh_atlas.png"
    Image.new("RGB", (64, 64), (90, 140, 200)).save(atlas)
    v, f, ids = _grid_mesh()
    tri = v[f]
    uv = np.stack([(v[:, 0] - X0) / NX, v[:, 1] / NY], axis=1).astype(np.float32)[f]
    cols = {f"{a}{k}": tri[:, k, i] for k in range(3) for i, a in enumerate("xyz")}
    cols |= {f"{a}{k}": uv[:, k, i] for k in range(3) for i, a in enumerate("uv")}
    cols |= {f"vid{k}": ids[f[:, k]] for k in range(3)}
    cols |= {"texture": np.zeros(len(f), np.int16), "src_face": np.arange(len(f), dtype=np.int64),
             "source": np.full(len(f), SOURCE, np.uint32)}
    grid = cfg.grid()
    tile_of_face = grid.tile_of_cells(grid.face_cells([cols[f"{a}{k}"] for k in range(3) for a in "xyz"], ORIGIN))
    bad = [_cell_key(cfg, i, j) for i, j in REPLACED_CELLS + [(13, 0)]]
    for t in TILES:
        rows = np.flatnonzero((tile_of_face[:, 0] == t.ix) & (tile_of_face[:, 1] == t.iy))
        _, faces, patches = build_tile_tables(None, {k: c[rows] for k, c in cols.items()}, grid, ORIGIN)
        meta = TileMeta(tile=t.key, patch_size_m=(1.0, 1.0, 1.0), crs="EPSG:32650", textures=(str(atlas),))
        write_tile_tables(wd.tile_dir(t), None, faces, patches, meta)
        keys = patches["patch"]
        write_side_table(wd.tile_dir(t), "labels", {"patch": keys, "label": np.isin(keys, bad).astype(np.int8)}, meta)
    return cfg, wd, tmp_path


def _region(cfg, tmp_path, perturb_m: float = 1e-4, duplicate: bool = True) -> RegionMesh:
    """The 2 x 2 m block of REPLACED_CELLS rebuilt as a fan around a raised centre vertex; its 8 border
    vertices carry the original vertex ids (positions perturbed by ``perturb_m``: welding must use the
    ids), plus (``duplicate``) a copy of the retained face in cell (8, 1) with the original ids."""
    ring = [(3, 1), (4, 1), (5, 1), (5, 2), (5, 3), (4, 3), (3, 3), (3, 2)]  # grid indices (x - X0, y)
    base = [[X0 + i, j, Z] for i, j in ring] + [[10.0, 2.0, Z + 0.1]]
    ids = [_vid(i, j) for i, j in ring] + [-1]
    faces = [[8, k, (k + 1) % 8] for k in range(8)]
    if duplicate:  # retained face (8,1) lower triangle: grid (2,1) (3,1) (3,2)
        base += [[X0 + 2, 1, Z], [X0 + 3, 1, Z], [X0 + 3, 2, Z]]
        ids += [_vid(2, 1), _vid(3, 1), _vid(3, 2)]
        faces += [[9, 10, 11]]
    atlas = tmp_path / "region_atlas.png"
    Image.new("RGB", (32, 32), (220, 120, 40)).save(atlas)
    base = np.array(base, np.float32)
    uv = np.clip((base[:, :2] - [9.0, 1.0]) / 2.0, 0, 1).astype(np.float32)
    pts = base + np.where(np.array(ids)[:, None] >= 0, perturb_m * np.array([1, -1, 1]), 0).astype(np.float32)
    faces = np.array(faces)
    return RegionMesh(region=REGION, vertices=pts, faces=faces, vertex_ids=np.array(ids, np.int64),
                      replaced_patches=np.array([_cell_key(cfg, i, j) for i, j in REPLACED_CELLS], np.int64),
                      corner_uv=uv[faces], atlas=str(atlas))


def _on_outer_border(edge) -> bool:
    """Whether an edge (two uint32-bit positions) runs along the outer border of the grid mesh."""
    p, q = (np.array(e, np.uint32).view(np.float32) for e in edge)
    return any(p[a] == q[a] and p[a] in (lo, hi) for a, lo, hi in ((0, X0, X0 + NX), (1, 0.0, NY)))


def _edge_counts(meshes) -> dict:
    """Undirected edges keyed by their two end positions (bit-exact), counted over the given TileMeshes."""
    counts: dict = {}
    for tm in meshes:
        pos = [tuple(p) for p in tm.vertices.view(np.uint32).tolist()]
        for a, b, c in tm.faces.tolist():
            for e in ((a, b), (b, c), (c, a)):
                key = tuple(sorted((pos[e[0]], pos[e[1]])))
                counts[key] = counts.get(key, 0) + 1
    return counts


# ------------------------------------------------------------------------------ kernels


def test_weld_kernels_on_three_faces():
    kid, first, _ = weld_keys(np.array([5, 6, 7, 7, 6, 8, 6, 5, 7]))
    assert kid.tolist() == [0, 1, 2, 2, 1, 3, 1, 0, 2] and first.tolist() == [0, 1, 2, 5]
    assert face_keep_mask(kid, 3).tolist() == [True, True, False]  # face 2 = face 0 in other orientation
    # corners of key 6 with two uvs: one split vertex, shared by both corners that carry the second uv
    w = weld_corners(np.array([5, 6, 7, 7, 6, 8]), np.zeros(6, np.int64), np.array([0, 0, 0, 0, 4, 0]))
    assert w.faces.tolist() == [[0, 1, 2], [2, 4, 3]] and w.n_split == 1
    w = weld_corners(np.full(6, 6), np.zeros(6, np.int64), np.array([1, 2, 1, 2, 3, 3]))
    assert w.faces.tolist() == [[0, 1, 0], [1, 2, 2]] and w.position_corner.tolist() == [0, 0, 0]


def test_region_mesh_checks_its_shapes_and_fingerprints_its_content():
    r = RegionMesh(region=4, vertices=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 2]]))
    moved = RegionMesh(region=4, vertices=np.ones((3, 3), np.float32), faces=np.array([[0, 1, 2]]))
    assert len(r.content_fingerprint()) == 32 and r.content_fingerprint() != moved.content_fingerprint()
    with pytest.raises(ValueError, match="an atlas needs corner_uv"):
        RegionMesh(region=1, vertices=np.zeros((3, 3), np.float32), faces=np.array([[0, 1, 2]]), atlas="a.png")
    with pytest.raises(ValueError, match="outside the vertices"):
        RegionMesh(region=1, vertices=np.zeros((2, 3), np.float32), faces=np.array([[0, 1, 2]]),
                   replaced_patches=np.zeros(0, np.int64))


# ------------------------------------------------------------------------------ a hand-made tile pair


def test_retained_mesh_alone_is_welded_by_id(handmade):
    cfg, wd, _ = handmade
    out = [run_merge_tile(t, cfg, wd) for t in TILES]
    assert [r["status"] for r in out] == ["done", "done"]
    meshes = [read_tile_mesh(wd.tile_dir(t)) for t in TILES]
    assert sum(m.n_faces for m in meshes) == 2 * NX * NY
    # one texture, one uv per grid vertex: no seam, so every vertex once per tile (5 x 5 each side)
    assert [m.n_vertices for m in meshes] == [5 * 5, 5 * 5]
    assert all(m.textures == [str(wd.root.parent / "mesh_atlas.png")] for m in meshes)
    grade = np.concatenate([m.grade for m in meshes])
    assert (grade == GRADE_BAD).sum() == 2 * 5 and (grade == GRADE_GOOD).sum() == 2 * NX * NY - 10


def test_rebuilt_region_replaces_its_patches_across_the_tile_border(handmade):
    cfg, wd, tmp = handmade
    region = _region(cfg, tmp)
    out = {t.key: run_merge_tile(t, cfg, wd, regions=[region]) for t in TILES}
    left, right = (read_tile_mesh(wd.tile_dir(t)) for t in TILES)
    # the 8 original faces of the 4 cells go; 8 fan faces come, 4 per tile (by their centroid's patch)
    assert out[TILES[0].key]["replaced_faces"] == 4 and out[TILES[1].key]["replaced_faces"] == 4
    assert [out[t.key]["rebuilt_faces"] for t in TILES] == [5, 4]  # + the duplicate, in cell (8, 1)
    assert out[TILES[0].key]["duplicates_dropped"] == 1 and out[TILES[0].key]["rebuilt_in_retained_patches"] == 1
    assert left.n_faces + right.n_faces == 2 * NX * NY
    for tm in (left, right):
        rebuilt = tm.source == SOURCE_REBUILT
        assert rebuilt.sum() == 4
        assert (tm.region[rebuilt] == REGION).all() and (tm.grade[rebuilt] == GRADE_BAD).all()
        assert (tm.region[~rebuilt] == -1).all() and (tm.source[~rebuilt] == SOURCE_MESH).all()
        assert tm.textures[tm.face_texture[rebuilt][0]].endswith("region_atlas.png")
        assert tm.textures[tm.face_texture[~rebuilt][0]].endswith("mesh_atlas.png")
        # no face twice, in either orientation, by position
        corners = tm.vertices[tm.faces].view(np.uint32).tolist()
        assert len({tuple(sorted(map(tuple, f))) for f in corners}) == tm.n_faces
    # watertight: every edge inside the mesh is used by exactly two faces (the tile-border edges once
    # per tile, so twice over both): the region border welded by id despite its 0.1 mm perturbation
    counts = _edge_counts([left, right])
    outer = {e for e in counts if _on_outer_border(e)}
    assert outer and all(counts[e] == 1 for e in outer)
    assert len(counts) > len(outer) and all(n == 2 for e, n in counts.items() if e not in outer)
    # the ring vertices sit at the retained positions (integers), the new centre vertex where repair put it
    rebuilt_xyz = np.concatenate([tm.vertices[tm.faces[tm.source == 1]].reshape(-1, 3) for tm in (left, right)])
    ring = rebuilt_xyz[np.abs(rebuilt_xyz[:, 2] - Z) < 0.01]
    assert np.array_equal(ring, np.round(ring * 2) / 2)
    assert np.isclose(rebuilt_xyz[:, 2].max(), Z + 0.1)


def test_rerun_skips_and_a_changed_region_redoes_its_tiles(handmade):
    cfg, wd, tmp = handmade
    region = _region(cfg, tmp)
    first = [run_merge_tile(t, cfg, wd, regions=[region]) for t in TILES]
    mtimes = [p.stat().st_mtime_ns for t in TILES for p in sorted(wd.tile_dir(t).glob("merged.*"))]
    again = [run_merge_tile(t, cfg, wd, regions=[region]) for t in TILES]
    assert all(r["skipped"] for r in again) and not any(r["skipped"] for r in first)
    assert mtimes == [p.stat().st_mtime_ns for t in TILES for p in sorted(wd.tile_dir(t).glob("merged.*"))]
    moved = _region(cfg, tmp, perturb_m=2e-4, duplicate=False)
    third = [run_merge_tile(t, cfg, wd, regions=[moved]) for t in TILES]
    assert not any(r["skipped"] for r in third)
    # the perturbed ring welds to the retained positions: the left tile loses only the duplicate
    # (dropped anyway), so its mesh is unchanged and not rewritten
    assert [r["rewritten"] for r in third] == [False, False]
    (wd.tile_dir(TILES[1]) / "labels.parquet").unlink()  # grades fall back to unknown: that tile only
    fourth = [run_merge_tile(t, cfg, wd, regions=[moved]) for t in TILES]
    assert [r["skipped"] for r in fourth] == [True, False] and fourth[1]["grades_from"] == "none"


def _write_region(cfg, wd, tmp, key: str, rm: RegionMesh, tiles: list[str]) -> None:
    """Write ``rm`` as repair does (``regions/{key}/``): the rows it replaces are the store rows of its
    replaced patches in each of ``tiles``."""
    from storage.contracts.region_mesh import write_region_doc, write_region_mesh
    from storage.patches.read import PatchStore
    from tasks.merge import faces_in_tile

    xyz = rm.vertices[rm.faces]
    _, face_patch = faces_in_tile(xyz, cfg.grid(), np.array(ORIGIN), TILES[0])
    rows = [np.flatnonzero(np.isin(PatchStore(wd.tile_dir(TileId.from_key(t))).read_all(
        point_columns=[], face_columns=["patch"])[1]["patch"], rm.replaced_patches)) for t in tiles]
    mesh = {"vertices": rm.vertices, "vertex_id": rm.vertex_ids, "vertex_source": np.zeros(len(rm.vertices)),
            "faces": rm.faces, "face_patch": face_patch, "uv": rm.corner_uv, "face_color": np.full((len(xyz), 3), 99),
            "replaced_tile": np.concatenate([np.full(len(r), i) for i, r in enumerate(rows)]),
            "replaced_row": np.concatenate(rows)}
    d = wd.root / "regions" / key
    write_region_mesh(d, mesh, np.zeros((1, 3)), np.zeros(1), np.full((8, 8, 3), 50, np.uint8))
    write_region_doc(d, {"status": "rebuilt", "replaced_tiles": tiles, "atlas": "atlas.jpg", "evidence": {}})


@pytest.fixture
def on_disk_regions(handmade):
    """The hand-made pair with two rebuilt regions on disk, as repair leaves them: "rx" (REPLACED_CELLS,
    across the tile border) and "ry" (one new face over cell (13, 0), right tile only)."""
    from storage.contracts.region_plan import Region, write_plan

    cfg, wd, tmp = handmade
    rx = _region(cfg, tmp, duplicate=False)
    ry = RegionMesh(region=9, vertices=np.array([[13.2, 0.2, Z], [13.8, 0.2, Z], [13.5, 0.8, Z]], np.float32),
                    faces=np.array([[0, 1, 2]]), vertex_ids=np.full(3, -1, np.int64),
                    replaced_patches=np.array([_cell_key(cfg, 13, 0)]), corner_uv=np.zeros((1, 3, 2), np.float32))
    keys = [np.array(sorted(r.replaced_patches), np.int64) for r in (rx, ry)]
    plan = [Region("rx", REGION, keys[0], keys[0], keys[0][:0], tiles=tuple(t.key for t in TILES)),
            Region("ry", 9, keys[1], keys[1], keys[1][:0], tiles=(TILES[1].key,))]
    write_plan(wd.root, plan, {}, {}, cfg.grid())
    _write_region(cfg, wd, tmp, "rx", rx, [t.key for t in TILES])
    _write_region(cfg, wd, tmp, "ry", ry, [TILES[1].key])
    return cfg, wd


def test_planning_reads_no_region_mesh_and_a_changed_region_file_reruns_only_its_tiles(on_disk_regions, monkeypatch):
    from storage.contracts import region_mesh
    from storage.contracts.region_mesh import region_files_for_tile, region_meshes_for_tile
    from tasks.units import MustRun, planning

    cfg, wd = on_disk_regions
    for t in TILES:  # the files' fingerprints are the loaded regions' own (no rerun after this change)
        assert ({(f.region, f.fingerprint) for f in region_files_for_tile(wd.root, t)}
                == {(m.region, m.fingerprint) for m in region_meshes_for_tile(wd.root, t)})
    first = [run_merge_tile(t, cfg, wd) for t in TILES]
    assert [(r["status"], r["regions"]) for r in first] == [("done", [REGION]), ("done", [REGION, 9])]
    assert [r["replaced_faces"] for r in first] == [4, 4 + 2]  # cell (13, 0) has two faces
    loads, real_load = [], np.load  # the region meshes read (np.load is numpy's: keep only regions/*)

    def counting_load(path, *a, **k):
        if Path(path).parent.parent.name == "regions":
            loads.append(Path(path).parent.name)
        return real_load(path, *a, **k)

    monkeypatch.setattr(region_mesh.np, "load", counting_load)

    def must_run() -> list[str]:
        out = []
        with planning(wd):
            for t in TILES:
                try:
                    run_merge_tile(t, cfg, wd)
                except MustRun:
                    out.append(t.key)
        return out

    assert must_run() == [] and loads == []  # nothing changed: nothing runs, no region mesh is read
    assert all(r["skipped"] for r in (run_merge_tile(t, cfg, wd) for t in TILES)) and loads == []
    ry_doc = wd.root / "regions" / "ry" / "region.json"
    ry_doc.write_text(ry_doc.read_text().replace('"evidence": {}', '"evidence": {"type": "hole"}'))
    assert must_run() == [TILES[1].key] and loads == []
    again = [run_merge_tile(t, cfg, wd) for t in TILES]
    assert [r["skipped"] for r in again] == [True, False] and sorted(loads) == ["rx", "ry"]  # its regions
    with np.load(wd.root / "regions" / "rx" / "mesh.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["vertices"][-1, 2] += 0.05  # the centre vertex raised: both tiles of rx rerun
    np.savez(wd.root / "regions" / "rx" / "mesh.npz", **arrays)
    assert must_run() == [t.key for t in TILES]
    ry_doc.write_text(ry_doc.read_text().replace('"rebuilt"', '"kept"'))  # left to the mesh: tile 1 only
    third = [run_merge_tile(t, cfg, wd) for t in TILES]
    assert not any(r["skipped"] for r in third) and third[1]["regions"] == [REGION]
    assert must_run() == []


def test_tile_without_store_loses_its_merged_mesh_and_bad_textures_fail(handmade):
    cfg, wd, tmp = handmade
    run_merge_tile(TILES[0], cfg, wd)
    d = wd.tile_dir(TILES[0])
    for name in ("patches.parquet", "faces.parquet", "points.parquet", "labels.parquet"):
        (d / name).unlink()
    assert run_merge_tile(TILES[0], cfg, wd) is None and not d.exists()
    (tmp / "mesh_atlas.png").unlink()
    res = run_merge_tile(TILES[1], cfg, wd)
    assert res["status"] == "failed" and "mesh_atlas.png" in res["error"] and "not found" in res["error"]


def test_weld_soup_keeps_untextured_colours_apart():
    xyz = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[1, 0, 0], [1, 1, 0], [0, 1, 0]]], np.float32)
    keys = np.array([[1, 2, 3], [2, 4, 3]])
    color = np.zeros((2, 3, 3), np.uint8)
    color[1] = 255  # the second face another colour: the shared edge's two vertices split
    soup = FaceSoup(xyz=xyz, keys=keys, uv=np.zeros((2, 3, 2), np.float32), texture=np.full(2, -1, np.int32),
                    color=color, grade=np.zeros(2, np.int8), source=np.zeros(2, np.int8),
                    region=np.full(2, -1, np.int32))  # fmt: skip
    tm, stats = weld_soup("0_0", soup, [])
    assert tm.uv is None and tm.textures == [] and tm.n_vertices == 6 and stats.split_vertices == 2
    assert tm.vertex_colors[tm.faces[1]].tolist() == [[255] * 3] * 3


# ------------------------------------------------------------------------------ the tiny synth campus


@pytest.fixture(scope="module")
def tiny_merged_run(tiny_campus, tmp_path_factory):
    """The tiny campus through the pipeline without classify and repair (inline, registration off, 25 m
    tiles), merged again here without regions."""
    from flows.campus import InlineExecutor, run_campus

    work = tmp_path_factory.mktemp("merge-tiny") / "work"
    cfg = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {
        "work_dir": str(work), "runner": "inline", "tiling.tile_size_m": 25.0, "registration.mode": "off",
        "classify.enabled": False, "repair.enabled": False})  # the retained mesh alone, graded by the labels
    run_campus(cfg, executor=InlineExecutor())
    wd = WorkDir(work)
    results = [run_merge_tile(t, cfg, wd) for t in wd.live_tiles()]
    return cfg, wd, results


def test_tiny_campus_merges_every_face_once(tiny_merged_run):
    from storage.patches.read import PatchStore

    _, wd, results = tiny_merged_run
    done = [r for r in results if r["status"] == "done"]
    assert len(done) >= 4 and all(r["status"] in ("done", "empty") for r in results)
    for r in done:
        store = PatchStore(wd.tile_dir(TileId.from_key(r["unit"])))
        tm = read_tile_mesh(wd.tile_dir(TileId.from_key(r["unit"])))
        assert tm.n_faces == store.n_faces - r["duplicates_dropped"] - r["degenerate_dropped"]
        assert r["duplicates_dropped"] + r["degenerate_dropped"] <= 0.001 * store.n_faces
        assert set(np.unique(tm.grade)) <= {GRADE_GOOD, GRADE_BAD} and (tm.source == SOURCE_MESH).all()
        assert tm.uv is not None and 1 <= len(tm.textures) <= 2  # one atlas per production tile it overlaps
        assert all(Path(t).is_file() for t in tm.textures)


def test_tiny_campus_merge_feeds_export_and_passes_its_checks(tiny_merged_run, tmp_path):
    from tasks.export import run_export
    from tasks.export.check import (
        check_mesh_features,
        check_tileset,
        ecef_round_trip_error_m,
        node_tools,
        validate_glbs,
    )

    _, wd0, results = tiny_merged_run
    work = tmp_path / "work"
    shutil.copytree(wd0.root, work, ignore=shutil.ignore_patterns("points.parquet", "staging", "scan"))
    summary = run_export(work)
    done = sorted(r["unit"] for r in results if r["status"] == "done")
    assert summary["tiles"] == len(done)
    assert summary["leaf_faces"] == sum(r["faces"] for r in results if r["status"] == "done")
    out = work / "output"
    assert check_tileset(out) == []
    glbs = sorted(out.rglob("*.glb"))
    assert all(check_mesh_features(g.read_bytes()) == [] for g in glbs)
    assert max(ecef_round_trip_error_m(work, t) for t in done) < 1e-3
    node, reason = node_tools()
    if node is None:
        pytest.fail(reason)
    reports = validate_glbs(glbs)
    assert not [r["messages"] for r in reports if r["errors"]]


def test_tiny_campus_rerun_skips_and_a_relabelled_tile_is_redone(tiny_merged_run, tmp_path):
    from storage.patches.read import PatchStore

    cfg0, wd0, results = tiny_merged_run
    work = tmp_path / "work"
    shutil.copytree(wd0.root, work, ignore=shutil.ignore_patterns("staging", "scan"))
    cfg, wd = cfg0.model_copy(update={"work_dir": str(work)}), WorkDir(work)
    again = [run_merge_tile(t, cfg, wd) for t in wd.live_tiles()]
    assert all(r["skipped"] for r in again)
    target = next(TileId.from_key(r["unit"]) for r in results if r["status"] == "done")
    store = PatchStore(wd.tile_dir(target))
    keys = store.patches()["patch"]
    write_side_table(wd.tile_dir(target), "labels", {"patch": keys, "label": np.ones(len(keys), np.int8)}, store.meta)
    third = {r["unit"]: r for r in (run_merge_tile(t, cfg, wd) for t in wd.live_tiles())}
    assert [k for k, r in third.items() if not r["skipped"]] == [target.key]
    assert third[target.key]["rewritten"] and (read_tile_mesh(wd.tile_dir(target)).grade == GRADE_BAD).all()


# ------------------------------------------------------------------------------ the run report


def test_report_renders_rebuilt_regions_before_and_after(handmade):
    from tasks.report import run_report

    cfg, wd, tmp = handmade
    for t in TILES:
        run_merge_tile(t, cfg, wd, regions=[_region(cfg, tmp)])
    res = run_report(cfg, wd)
    page = Path(res["report"]).read_text()
    assert res["figures"] == ["class_map", f"region_{REGION:06d}"] and res["truth"] is None
    for name in res["figures"]:
        assert f'id="{name}"' in page
    assert page.count("data:image/png;base64,") == 2 and "No truth for these inputs" in page
    assert (wd.report_dir / "regions" / f"region_{REGION:06d}.png").stat().st_size > 5_000
    assert "ms3d view" in page and "merge" in page  # the stage table names the merge stage


def test_region_renders_are_kept_and_drawn_again_when_a_merged_tile_changes(handmade, monkeypatch):
    # the flow draws the renders beside the export; the report then reads them back unless their inputs changed
    import tasks.report.stage as report_stage
    from tasks.report import region_renders, region_renders_fresh

    cfg, wd, tmp = handmade
    for t in TILES:
        run_merge_tile(t, cfg, wd, regions=[_region(cfg, tmp)])
    assert not region_renders_fresh(cfg, wd)
    sec, rebuilt = region_renders(cfg, wd)
    assert rebuilt and list(sec.figures) == [f"region_{REGION:06d}"] and region_renders_fresh(cfg, wd)
    drawn, real = [], report_stage.regions_section
    monkeypatch.setattr(report_stage, "regions_section", lambda *a: drawn.append(1) or real(*a))
    kept, _ = region_renders(cfg, wd)
    assert not drawn and kept.figures == sec.figures and kept.body == sec.body
    for t in TILES:  # merged again without the region: the kept renders are stale
        run_merge_tile(t, cfg, wd, regions=[])
    assert not region_renders_fresh(cfg, wd)
    now, rebuilt_now = region_renders(cfg, wd)
    assert drawn and not rebuilt_now and not now.figures


def test_tiny_campus_report_names_its_figures_and_caches_quality(tiny_merged_run, tmp_path):
    from tasks.export import run_export
    from tasks.report import run_report

    cfg0, wd0, _ = tiny_merged_run
    work = tmp_path / "work"
    shutil.copytree(wd0.root, work, ignore=shutil.ignore_patterns("staging", "scan"))
    cfg, wd = cfg0.model_copy(update={"work_dir": str(work)}), WorkDir(work)
    run_export(work)
    res = run_report(cfg, wd)
    page = Path(res["report"]).read_text()
    assert res["figures"] == ["patch_faces_histogram", "patch_points_histogram", "class_map"]
    assert all(f'id="{n}"' in page for n in res["figures"]) and page.count("data:image/png;base64,") == 3
    for words in ("Registration (MLS → mesh)", "Tile_+001_+000.obj", "F@5 cm", "merged model", 'href="tileset.json"',
                  f"ms3d view {work}", "partition", "merge"):
        assert words in page, words
    assert "Could not make this section" not in page
    quality = (wd.report_dir / "quality.json").stat().st_mtime_ns
    run_report(cfg, wd)  # quality comes from the cache: the merged tiles did not change
    assert (wd.report_dir / "quality.json").stat().st_mtime_ns == quality


def test_a_merged_model_the_repair_left_alone_scores_exactly_the_input_mesh(tiny_merged_run, tiny_campus):
    """The quality stage's input row is the ingested mesh, so retained faces get the same samples in both rows:
    the rows differ only where a region was rebuilt (the raw file would differ by ingest's splits and float32)."""
    from tasks.quality.stage import MODELS, merged_tiles, quality_share

    _, wd, _ = tiny_merged_run
    origin = campus_frame(read_campus(wd)).origin_array
    shares = quality_share(wd, tiny_campus, origin, merged_tiles(wd), True, (0, 1))
    merged, given = (shares[m].report().to_dict() for m in MODELS)
    assert merged["evaluated_area_m2"] > 0 and merged["fscore"][0] < 1.0  # something to tell apart
    for name in ("precision", "recall", "fscore", "uncovered_fraction", "chamfer_m"):
        assert merged[name] == given[name], name
    assert merged["per_class"] == given["per_class"]


def test_thinned_points_read_in_windows_equal_the_whole_tile_strided(tiny_work):
    """The face-quality points of a tile: every stride-th row, read a window at a time (bounded memory), the
    same rows as reading the whole table and striding it."""
    from storage.patches.read import PatchStore
    from tasks.merge.stage import thinned_points

    _, wd = tiny_work
    tile_dir = max((p.parent for p in (wd.root / "tiles").glob("*/points.parquet")),
                   key=lambda d: PatchStore(d).n_points)
    store = PatchStore(tile_dir)
    whole = store.read_all_stacked("points", ["x", "y", "z"])
    assert len(whole) > 5000
    for max_points, window in ((1000, 777), (len(whole) // 3, 4096), (len(whole), 100)):
        got, stride = thinned_points(store, max_points, window)
        assert stride == max(1, -(-len(whole) // max_points)) and len(got) <= max_points
        np.testing.assert_array_equal(got, whole[::stride])
