"""Export to 3D Tiles: glb writer, georeferencing round trip, tileset structure, validator, reruns."""

from __future__ import annotations

import json
import shutil
import sys

import numpy as np
import pytest

from storage.contracts.tile_mesh import read_tile_mesh, write_tile_mesh
from storage.errors import InputError
from tasks.config import ExportConfig
from tasks.export import run_export
from tasks.export.check import check_mesh_features, check_tileset, node_tools, validate_glbs
from tasks.export.georef import EnuProjector, enu_to_gltf, gltf_to_enu, make_georef
from tasks.export.gltf import GltfMesh, build_glb, glb_primitives, read_glb, split_by_feature
from tasks.export.tree import plan_quadtree


def _ecef_direct(crs: str, world: np.ndarray) -> np.ndarray:
    """ECEF straight from projected world coordinates with pyproj; the orthometric heights of a compound CRS
    (PROJ without its geoid grid takes them as ellipsoidal) raised by the shipped EGM96 N along the normal."""
    from pyproj import CRS, Transformer

    from storage.geoid import egm96_undulation

    src = CRS(crs)
    src = src if src.is_compound else src.to_3d()
    x, y, z = Transformer.from_crs(src, "EPSG:4978", always_xy=True).transform(*world.T)
    if not src.is_compound:
        return np.stack([x, y, z], axis=1)
    lon, lat, h = Transformer.from_crs(src, "EPSG:4979", always_xy=True).transform(*world.T)
    x, y, z = Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(
        lon, lat, np.asarray(h) + egm96_undulation(np.asarray(lat), np.asarray(lon)))
    return np.stack([x, y, z], axis=1)


def _through_tileset(tileset: dict, gltf_positions: np.ndarray) -> np.ndarray:
    """What a 3D Tiles client does: glTF y-up -> z-up, then the root transform (column-major)."""
    m = np.asarray(tileset["root"]["transform"], np.float64).reshape(4, 4).T
    enu = gltf_to_enu(gltf_positions)
    return enu @ m[:3, :3].T + m[:3, 3]


def _two_feature_mesh() -> GltfMesh:
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 0, -1], [0, 0, -1], [2, 0, 0]], np.float32)
    faces = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    return GltfMesh(positions=positions, faces=faces, feature=np.array([0, 0, 1]), grade=np.array([0, 1], np.int8),
                    source=np.array([0, 1], np.int8), region=np.array([-1, 7], np.int32),
                    face_texture=np.full(3, -1, np.int16), vertex_colors=np.full((5, 3), 200, np.uint8))


def test_split_by_feature_duplicates_only_shared_vertices():
    faces, src, fid = split_by_feature(np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]]), np.array([0, 0, 1]))
    assert len(src) == 7  # 5 vertices, 1 and 2 shared across the two features
    assert (fid[faces] == np.array([0, 0, 1])[:, None]).all()
    assert sorted(src.tolist()) == [0, 1, 1, 2, 2, 3, 4]


def test_glb_round_trip_and_feature_table():
    data = build_glb(_two_feature_mesh())
    doc, _ = read_glb(data)
    assert len(data) % 4 == 0 and doc["asset"]["version"] == "2.0"
    (prim,) = glb_primitives(data)
    ids = prim["_FEATURE_ID_0"][prim["indices"]]
    assert sorted(np.unique(ids[:, 0]).tolist()) == [0, 1]
    # the face of feature 1 is (1, 4, 2) and feature 1 is (bad, rebuilt, region 7)
    face1 = prim["POSITION"][prim["indices"][ids[:, 0] == 1][0]]
    assert sorted(face1[:, 0].tolist()) == [1.0, 1.0, 2.0]
    table = doc["extensions"]["EXT_structural_metadata"]["propertyTables"][0]
    assert table["count"] == 2 and set(table["properties"]) == {"grade", "source", "region"}
    assert check_mesh_features(data) == []
    assert np.allclose(np.linalg.norm(prim["NORMAL"], axis=1), 1.0, atol=1e-6)


def test_glb_draco_round_trip():
    pytest.importorskip("DracoPy", reason="DracoPy not installed (pip install DracoPy)")
    plain, draco = build_glb(_two_feature_mesh()), build_glb(_two_feature_mesh(), "draco")
    doc, _ = read_glb(draco)
    assert doc["extensionsRequired"] == ["KHR_draco_mesh_compression"]
    (prim,) = glb_primitives(draco)
    assert check_mesh_features(draco) == []
    assert np.abs(np.sort(prim["POSITION"], axis=0) - np.sort(glb_primitives(plain)[0]["POSITION"], axis=0)).max() < 1e-3


def test_plan_quadtree_parents_cover_children():
    tree = plan_quadtree(["3_4", "4_4", "5_6", "3_5"])
    assert len(tree.levels) == 3 and len(tree.levels[-1]) == 1
    for parent, kids in tree.children.items():
        assert all(k.parent == parent for k in kids)
    assert sorted(tree.leaf_tile.values()) == ["3_4", "3_5", "4_4", "5_6"]


def test_enu_is_not_the_projected_grid_and_round_trips_below_1mm():
    """1 km from the ENU origin the grid differs from ENU by metres; the tileset chain still lands < 1 mm."""
    for crs, origin in (("EPSG:32650", (589000.0, 2712000.0, 15.0)), ("EPSG:7415", (92000.0, 437000.0, 0.0))):  # Rotterdam, 1 deg west of RD's centre
        georef = make_georef(crs, origin, (0.0, 0.0, 0.0))
        local = np.array([[900.0, -700.0, 30.0], [-1000.0, 1000.0, 2.5], [0.5, 0.25, 0.0]])
        enu = EnuProjector(georef).local_to_enu(local)
        assert np.abs(enu[0, :2] - local[0, :2]).max() > 0.5  # grid convergence + scale: not a shift
        tileset = {"root": {"transform": georef.tileset_transform()}}
        ecef = _through_tileset(tileset, enu_to_gltf(enu))
        direct = _ecef_direct(crs, local + np.asarray(origin))
        assert np.linalg.norm(ecef - direct, axis=1).max() < 1e-3, crs


def test_compound_crs_records_vertical_assumption():
    georef = make_georef("EPSG:7415", (155000.0, 463000.0, 0.0), (0.0, 0.0, 0.0))
    doc = georef.to_json()
    assert doc["source_crs"] == "EPSG:7415" and "NAP" in " ".join(doc["assumptions"])
    assert any("made ellipsoidal with the EGM96" in a for a in doc["assumptions"]) and doc["geoid"] == "egm96"
    assert any("EGM96 stands in for the geoid model of NAP height" in a for a in doc["assumptions"])
    assert "Ballpark geographic offset" not in doc["operation"] and "EGM96 geoid" in doc["operation"]
    assert 52.0 < doc["enu_origin_wgs84"]["lat_deg"] < 52.3


def test_nap_zero_lands_at_the_geoid_in_amsterdam(tmp_path):
    """NAP 0 m in Amsterdam: ~43 m above the ellipsoid with the shipped EGM96 (42.94 m), exactly a user grid's
    N with export.geoid_grid; a CRS with ellipsoidal heights applies no geoid."""
    from storage.geoid import egm96_undulation, write_gtx

    ams = (121000.0, 487000.0, 0.0)  # RD New, NAP 0 m
    g = make_georef("EPSG:7415", ams, (0.0, 0.0, 0.0))
    assert g.height_m == pytest.approx(float(egm96_undulation(g.lat_deg, g.lon_deg)), abs=1e-3)
    assert 42.5 < g.height_m < 43.5
    # the same point through the projector chain: local (0, 0, 0) is the ENU origin
    assert np.abs(EnuProjector(g).local_to_enu(np.zeros((1, 3)))).max() < 1e-6
    lat, lon = np.arange(50.0, 54.01, 0.25), np.arange(3.0, 7.01, 0.25)
    n = 40.0 + (lat[:, None] - 50.0) + 0.5 * (lon[None, :] - 3.0)  # a linear "national" geoid
    grid = write_gtx(tmp_path / "nl.gtx", 50.0, 3.0, 0.25, 0.25, n)
    g2 = make_georef("EPSG:7415", ams, (0.0, 0.0, 0.0), geoid_grid=str(grid))
    assert g2.height_m == pytest.approx(40.0 + (g2.lat_deg - 50.0) + 0.5 * (g2.lon_deg - 3.0), abs=1e-3)
    assert g2.geoid == str(grid) and "nl.gtx" in g2.operation
    p2 = EnuProjector(g2)  # rebuilt from the georef alone, as export nodes and the label server do
    assert np.abs(p2.local_to_enu(np.array([[0.0, 0.0, 0.0]]))).max() < 1e-6
    plain = make_georef("EPSG:32650", (589000.0, 2712000.0, 15.0), (0.0, 0.0, 0.0))
    assert plain.geoid is None and plain.height_m == pytest.approx(15.0, abs=1e-3)


def test_export_writes_a_valid_tileset(tiny_export):
    work, summary = tiny_export
    out = work / "output"
    assert summary["tiles"] == 6 and summary["leaf_faces"] == summary["faces_in"] > 100_000
    assert check_tileset(out) == []
    doc = json.loads((out / "tileset.json").read_text())
    assert doc["asset"]["version"] == "1.1" and doc["root"]["refine"] == "REPLACE"
    assert len(doc["root"]["transform"]) == 16

    def walk(t):
        yield t
        for c in t.get("children", []):
            yield from walk(c)

    tiles = list(walk(doc["root"]))
    leaves = [t for t in tiles if "children" not in t]
    parents = [t for t in tiles if "children" in t]
    assert len(leaves) == 6 and all(t["geometricError"] == 0 for t in leaves)
    # measured, not a constant: positive, different per parent, decimetres for a 4x decimation
    errors = [t["geometricError"] for t in parents]
    assert all(0.005 < e < 2.0 for e in errors) and len(set(errors)) == len(errors)
    georef = json.loads((out / "georef.json").read_text())
    assert georef["source_crs"] == "EPSG:32650" and georef["frame_origin"] == [589000.0, 2712000.0, 15.0]
    assert (out / "overview.glb").stat().st_size > 10_000


def test_export_vertices_round_trip_to_ecef_below_1mm(tiny_export):
    from scipy.spatial import cKDTree

    work, _ = tiny_export
    out = work / "output"
    doc = json.loads((out / "tileset.json").read_text())
    tm = read_tile_mesh(work / "tiles" / "1_1")
    positions = np.concatenate([p["POSITION"] for p in glb_primitives((out / "content/tiles/1_1.glb").read_bytes())])
    via_tileset = _through_tileset(doc, positions)
    world = tm.vertices.astype(np.float64) + np.array([589000.0, 2712000.0, 15.0])
    direct = _ecef_direct("EPSG:32650", world)
    dist, _ = cKDTree(direct).query(via_tileset)
    assert dist.max() < 1e-3, f"max {dist.max() * 1000:.3f} mm"


def test_every_glb_passes_gltf_validator(tiny_export):
    node, reason = node_tools()
    if node is None:
        pytest.fail(reason)
    work, _ = tiny_export
    glbs = sorted((work / "output").rglob("*.glb"))
    reports = validate_glbs(glbs)
    assert len(reports) == len(glbs) == 6 + 2 + 1 + 1  # leaves, lod1, root, overview
    errors = {r["path"]: r["messages"] for r in reports if r["errors"]}
    assert not errors, errors
    assert sum(r["warnings"] for r in reports) == 0
    for g in glbs:
        assert check_mesh_features(g.read_bytes()) == [], g


def test_rerun_rewrites_only_the_changed_tile_and_its_ancestors(tiny_export, tmp_path):
    work0, first = tiny_export
    work = tmp_path / "work"
    shutil.copytree(work0, work)
    again = run_export(work)
    assert again["built"] == [] and len(again["reused"]) == first["nodes"]
    out = work / "output"
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*.glb")}

    tm = read_tile_mesh(work / "tiles" / "2_0")
    from dataclasses import replace

    write_tile_mesh(work / "tiles" / "2_0", replace(tm, grade=np.zeros_like(tm.grade)))
    third = run_export(work)
    assert third["built"] == ["L0_2_0", "L1_1_0", "L2_0_0"]
    changed = {p.relative_to(out).as_posix() for p in out.rglob("*.glb") if p.stat().st_mtime_ns != before.get(p)}
    assert changed == {"content/tiles/2_0.glb", "content/lod1/1_0.glb", "content/lod2/0_0.glb", "overview.glb"}
    assert check_tileset(out, read_content=False) == []

    shutil.rmtree(work / "tiles" / "2_0")  # a tile gone: its content and cached LOD go too
    fourth = run_export(work)
    assert fourth["built"] == ["L1_1_0", "L2_0_0"] and fourth["tiles"] == 5
    assert not (out / "content/tiles/2_0.glb").exists() and not (work / "export/lod/L0_2_0.npz").exists()
    assert check_tileset(out) == []


def test_overview_is_rebuilt_when_it_was_not_built_from_the_current_root(tiny_export, tmp_path):
    """An overview left from another root (an export stopped between a root and its overview, or a root
    that is a reused node) is rebuilt although every node is reused."""
    work0, _ = tiny_export
    work = tmp_path / "work"
    shutil.copytree(work0, work)
    state_path, overview = work / "output" / "tileset.fingerprints.json", work / "output" / "overview.glb"
    state = json.loads(state_path.read_text())
    assert state["overview"] == state["nodes"]["L2_0_0"]["fingerprint"]
    state_path.write_text(json.dumps(state | {"overview": "another root"}))
    mtime = overview.stat().st_mtime_ns
    again = run_export(work)
    assert again["built"] == [] and overview.stat().st_mtime_ns != mtime
    assert json.loads(state_path.read_text())["overview"] == state["overview"]
    mtime = overview.stat().st_mtime_ns
    run_export(work)
    assert overview.stat().st_mtime_ns == mtime


def test_draco_export_validates_and_is_smaller(tiny_merged, tiny_export, tmp_path):
    pytest.importorskip("DracoPy", reason="DracoPy not installed (pip install DracoPy)")
    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work, ignore=shutil.ignore_patterns("1_*", "2_*"))  # tiles 0_0, 0_1
    summary = run_export(work, ExportConfig(compression="draco"))
    out = work / "output"
    assert summary["tiles"] == 2 and check_tileset(out) == []
    for leaf in ("content/tiles/0_0.glb", "content/tiles/0_1.glb"):  # same textures, compressed geometry
        assert (out / leaf).stat().st_size < (tiny_export[0] / "output" / leaf).stat().st_size
    node, reason = node_tools()
    if node is None:
        pytest.fail(reason)
    reports = validate_glbs(sorted(out.rglob("*.glb")))
    assert all(r["errors"] == 0 for r in reports), [r["messages"] for r in reports if r["errors"]]


def test_export_errors_name_the_problem(tmp_path, tiny_merged):
    with pytest.raises(InputError, match="campus.json"):
        run_export(tmp_path)
    work = tmp_path / "w"
    shutil.copytree(tiny_merged, work, ignore=shutil.ignore_patterns("tiles"))
    with pytest.raises(InputError, match="no merged tiles"):
        run_export(work)


def test_process_pool_gives_the_same_tileset(tiny_merged, tmp_path):
    runs = []
    for workers in (1, 2):
        work = tmp_path / f"w{workers}"
        shutil.copytree(tiny_merged, work, ignore=shutil.ignore_patterns("1_*", "2_*"))  # tiles 0_0, 0_1
        run_export(work, workers=workers)
        runs.append(work / "output")
    assert (runs[0] / "tileset.json").read_bytes() == (runs[1] / "tileset.json").read_bytes()
    for glb in runs[0].rglob("*.glb"):
        assert glb.read_bytes() == (runs[1] / glb.relative_to(runs[0])).read_bytes(), glb


def test_nodes_mapped_in_batches_give_the_same_tileset_and_record_each_node(tiny_merged, tiny_export, tmp_path):
    from storage.workdir.layout import WorkDir
    from storage.workdir.manifest import read_record
    from tasks.export import build_nodes, node_batches, node_records

    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work)
    sizes = []

    def map_jobs(jobs):  # what the flow does, without the cluster: batches in, records in job order out
        batches = node_batches(jobs, 2)
        sizes.append([len(b) for b in batches])
        return node_records([r for b in reversed(batches) for r in build_nodes(b)], len(jobs))

    summary = run_export(work, map_jobs=map_jobs)
    assert sizes == [[1] * 6, [1, 1], [1], [1]]  # 6 leaves, 2 parents, the root, the overview
    assert (work / "output/tileset.json").read_bytes() == (tiny_export[0] / "output/tileset.json").read_bytes()
    for key in summary["built"] + ["L-1_0_0"]:
        rec = read_record(WorkDir(work), "export", key)
        assert rec.status == "done" and rec.summary["uri"] and rec.seconds > 0, key
    assert [len(b) for b in node_batches(list(range(10)), 2)] == [1] * 10  # up to 8 per worker: one node each
    assert [len(b) for b in node_batches(list(range(20)), 2)] == [2, 2, 2, 2] + [1] * 12  # the heavier first
    with pytest.raises(InputError, match="L0_1_0: disk full"):
        node_records([{"index": 0, "status": "done", "record": {}},
                      {"index": 1, "status": "failed", "error": "L0_1_0: disk full"}], 2)
    with pytest.raises(InputError, match="an export task failed"):
        node_records([{"status": "failed", "error": "worker lost"}], 1)


def test_the_pymeshlab_decimator_missing_is_one_line_and_auto_is_pyfqmr(monkeypatch):
    from tasks.export.lod import LodMesh, decimate, quadric_backend

    monkeypatch.setitem(sys.modules, "pymeshlab", None)  # as if not installed: its import fails
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 0, 0], [2, 1, 0]], np.float32)
    faces = np.array([[0, 1, 2], [1, 3, 2], [1, 4, 3], [4, 5, 3]], np.int32)
    lod = LodMesh(pos, faces, np.zeros((6, 3), np.uint8), *(np.zeros(4, t) for t in (np.int8, np.int8, np.int32)))
    with pytest.raises(InputError, match=r"^decimator 'pymeshlab' needs pymeshlab \(GPL\), which is not installed"):
        decimate(lod, 2, samples=100, backend="pymeshlab")
    assert quadric_backend() == "fqmr"


@pytest.mark.parametrize("backend", ["fqmr", "pymeshlab"])
def test_decimate_measures_its_deviation_and_keeps_borders(backend):
    if backend == "pymeshlab":
        pytest.importorskip("pymeshlab", reason="pymeshlab (GPL, the gpl extra) not installed")
    from tasks.export.lod import LodMesh, decimate

    n = 61  # a 60 x 60 grid of 1 m cells with a 2 m bump: 7,200 faces
    x, y = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
    z = 2.0 * np.exp(-((x - 30) ** 2 + (y - 30) ** 2) / 60.0)
    pos = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.float32)
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([i, i + 1, i + n], 1), np.stack([i + 1, i + n + 1, i + n], 1)]).astype(np.int32)
    m = len(faces)
    lod = LodMesh(pos, faces, np.full((len(pos), 3), 100, np.uint8), np.zeros(m, np.int8), np.zeros(m, np.int8),
                  np.where(np.arange(m) % 2 == 0, 3, -1).astype(np.int32))
    dec = decimate(lod, m // 4, samples=5000, backend=backend)
    assert 0.15 * m < dec.mesh.n_faces <= 0.3 * m
    assert 0.0 < dec.mean_m < dec.hausdorff_m < 0.5  # a bump of 2 m, decimated 4x: centimetres, not zero
    border = {(float(a), float(b)) for a, b, _ in pos if a in (0, n - 1) or b in (0, n - 1)}
    kept = {(float(a), float(b)) for a, b, _ in dec.mesh.positions}
    assert len(border - kept) < 0.1 * len(border)  # open borders stay where the neighbour tile expects them
    assert set(np.unique(dec.mesh.region).tolist()) == {-1, 3}


def test_meshopt_and_ktx2_export_validate_and_keep_metadata(tiny_merged, tiny_export, tmp_path):
    """export.compression meshopt + export.texture ktx2 (glTF-Transform and a Basis encoder in node; small
    atlases to stay fast): 0 validator errors, both extensions in every textured leaf, and the viewer decodes
    them to the same per-face grades as the uncompressed export, without errors."""
    import subprocess

    from flows.view import VIEWER_DIR, start_viewer

    node, reason = node_tools()
    if node is None:
        pytest.fail(reason)
    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work)
    summary = run_export(work, ExportConfig(compression="meshopt", texture="ktx2", max_texture_px=256))
    out = work / "output"
    assert summary["compression"] == "meshopt" and check_tileset(out, read_content=False) == []
    for leaf in sorted((out / "content" / "tiles").glob("*.glb")):
        doc, _ = read_glb(leaf.read_bytes())
        assert "EXT_meshopt_compression" in doc["extensionsRequired"] and "EXT_structural_metadata" in doc["extensions"]
        if doc.get("images"):
            assert "KHR_texture_basisu" in doc["extensionsRequired"]
            assert all(im["mimeType"] == "image/ktx2" for im in doc["images"])
    reports = validate_glbs(sorted(out.rglob("*.glb")))
    assert all(r["errors"] == 0 for r in reports), [r["messages"] for r in reports if r["errors"]]
    faces = {}
    for name, w in (("plain", tiny_export[0]), ("compressed", work)):
        server = start_viewer(w)
        try:
            run = subprocess.run([node, str(VIEWER_DIR / "screenshot.mjs"), server.url + "&errorTarget=0&mode=texture",
                                  str(tmp_path / f"{name}.png"), "800", "600", "120000"], check=False,
                                 capture_output=True, text=True, timeout=180)
        finally:
            server.stop()
        assert run.returncode == 0, run.stderr[-2000:]
        result = json.loads(run.stdout)
        assert result["ready"] and not result["state"]["errors"], result
        bad = [m for m in result["console"] if m.startswith("pageerror") or any(
            w in m.lower() for w in ("ktx", "basis", "transcod", "meshopt", "decod"))]
        assert not bad, bad
        faces[name] = result["state"]["faces"]
    assert faces["compressed"] == faces["plain"] and faces["plain"]["good"] > 0
    with pytest.raises(ValueError, match="ktx2 goes with"):
        ExportConfig(compression="draco", texture="ktx2")
