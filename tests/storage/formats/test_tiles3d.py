"""3D Tiles tilesets as a mesh input (storage.formats.tiles3d): ms3d's own export read back lands on the
merged model it was written from; b3dm content with RTC_CENTER, external tilesets and bad input."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.meshes import read_mesh
from storage.formats.tiles3d import ecef_to_crs, read_tileset
from storage.workdir.layout import WorkDir


def _merged_world(work):
    """The merged model of a work dir in world metres: (vertices (n, 3) float64, n_faces, area m^2)."""
    from storage.contracts.tile_mesh import read_tile_mesh
    from storage.workdir.layout import campus_frame, read_campus

    origin = np.asarray(campus_frame(read_campus(WorkDir(work))).origin, np.float64)
    verts, n_faces, area = [], 0, 0.0
    for d in sorted((work / "tiles").glob("*/merged.json")):
        tm = read_tile_mesh(d.parent)
        v = np.asarray(tm.vertices, np.float64) + origin
        t = v[tm.faces]
        area += float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())
        verts.append(v)
        n_faces += len(tm.faces)
    return np.concatenate(verts), n_faces, area


def test_own_export_reads_back_onto_the_merged_model(tiny_export):
    from scipy.spatial import cKDTree

    from storage.workdir.layout import campus_frame, read_campus

    work, summary = tiny_export
    crs = campus_frame(read_campus(WorkDir(work))).crs
    mesh = read_mesh(work / "output" / "tileset.json")
    assert mesh.n_faces == summary["leaf_faces"]  # the finest level only, every face
    assert mesh.face_texture is not None and mesh.textures and not mesh.embedded_textures  # refs, no pixels
    world = ecef_to_crs(mesh.vertices, crs)
    truth, n_faces, area = _merged_world(work)
    assert mesh.n_faces == n_faces
    d, _ = cKDTree(truth).query(world)
    assert d.max() < 1e-3, d.max()  # float32 ENU and PROJ both ways: well under a millimetre
    t = world[mesh.faces]
    got_area = float(0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1).sum())
    assert got_area == pytest.approx(area, rel=1e-5)


def test_implicit_export_reads_back_like_the_explicit_one(tiny_merged, tiny_export, tmp_path):
    import shutil

    from tasks.config import ExportConfig
    from tasks.export import run_export

    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work)
    run_export(work, ExportConfig(tiling="implicit", subtree_levels=2))
    implicit = read_mesh(work / "output" / "tileset.json")
    explicit = read_mesh(tiny_export[0] / "output" / "tileset.json")
    assert implicit.n_faces == explicit.n_faces == tiny_export[1]["leaf_faces"]
    a = np.sort(implicit.vertices[implicit.faces].reshape(-1, 3), axis=0)
    b = np.sort(explicit.vertices[explicit.faces].reshape(-1, 3), axis=0)
    assert np.abs(a - b).max() < 1e-6 * np.abs(b).max()
    sub = max((work / "output" / "subtrees").rglob("*.subtree"))
    sub.write_bytes(sub.read_bytes()[:20])  # truncated: one line naming the subtree
    with pytest.raises(InputError, match="subtree") as e:
        read_mesh(work / "output" / "tileset.json")
    assert str(sub) in str(e.value) and "\n" not in str(e.value)


def _glb_triangle() -> bytes:
    """A minimal glb: one triangle (0,0,0), (1,0,0), (0,0,-1) in glTF Y-up = east, north in Z-up."""
    pos = np.array([[0, 0, 0], [1, 0, 0], [0, 0, -1]], np.float32).tobytes()
    doc = {"asset": {"version": "2.0"}, "scene": 0, "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0}],
           "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
           "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                          "min": [0, 0, -1], "max": [1, 0, 0]}],
           "bufferViews": [{"buffer": 0, "byteLength": len(pos)}], "buffers": [{"byteLength": len(pos)}]}
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    body = struct.pack("<I4s", len(js), b"JSON") + js + struct.pack("<I4s", len(pos), b"BIN\x00") + pos
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


def _b3dm(glb: bytes, rtc) -> bytes:
    ft = json.dumps({"BATCH_LENGTH": 0, "RTC_CENTER": list(rtc)}).encode()
    ft += b" " * (-(28 + len(ft)) % 8)
    return struct.pack("<4s6I", b"b3dm", 1, 28 + len(ft) + len(glb), len(ft), 0, 0, 0) + ft + glb


def test_b3dm_rtc_external_tileset_and_transforms(tmp_path):
    shift = np.eye(4)
    shift[:3, 3] = [1000.0, 2000.0, 3000.0]
    (tmp_path / "a.b3dm").write_bytes(_b3dm(_glb_triangle(), [10.0, 20.0, 30.0]))
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.glb").write_bytes(_glb_triangle())
    (tmp_path / "sub" / "tileset.json").write_text(json.dumps(
        {"asset": {"version": "1.1"}, "geometricError": 0,
         "root": {"geometricError": 0, "boundingVolume": {"sphere": [0, 0, 0, 5]}, "content": {"uri": "b.glb"}}}))
    (tmp_path / "tileset.json").write_text(json.dumps(
        {"asset": {"version": "1.0"}, "geometricError": 10,
         "root": {"geometricError": 10, "boundingVolume": {"sphere": [0, 0, 0, 1e4]}, "refine": "REPLACE",
                  "transform": shift.T.reshape(-1).tolist(), "content": {"uri": "a.b3dm"},
                  "children": [{"geometricError": 0, "boundingVolume": {"sphere": [0, 0, 0, 1e4]},
                                "content": {"uri": "a.b3dm"}},
                               {"geometricError": 0, "boundingVolume": {"sphere": [0, 0, 0, 1e4]},
                                "transform": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 5, 0, 0, 1],
                                "content": {"uri": "sub/tileset.json"}}]}}))
    m = read_tileset(tmp_path / "tileset.json")
    assert m.n_faces == 2  # the two leaves, not the root's coarser content
    tri = np.sort(m.vertices[m.faces].reshape(-1, 3), axis=0)
    expect_a = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) + [10, 20, 30] + [1000, 2000, 3000]  # Z-up, RTC, root
    expect_b = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]]) + [5, 0, 0] + [1000, 2000, 3000]  # child transform too
    assert np.allclose(tri, np.sort(np.concatenate([expect_a, expect_b]), axis=0))


@pytest.mark.parametrize("what, says", [("notile", "not a 3D Tiles tileset"), ("pnts", "not a mesh"),
                                        ("missing", "tile content not found"), ("empty", "no mesh content"),
                                        ("junk", "not a readable JSON")])
def test_bad_tilesets_are_one_line(tmp_path, what, says):
    doc = {"asset": {"version": "1.1"}, "geometricError": 1, "root": {"geometricError": 0,
           "boundingVolume": {"sphere": [0, 0, 0, 1]}, "content": {"uri": "c.glb"}}}
    path = tmp_path / "tileset.json"
    if what == "notile":
        doc = {"hello": 1}
    elif what == "pnts":
        doc["root"]["content"]["uri"] = "c.pnts"
        (tmp_path / "c.pnts").write_bytes(b"pnts")
    elif what == "empty":
        del doc["root"]["content"]
    path.write_text("{oops" if what == "junk" else json.dumps(doc))
    with pytest.raises(InputError, match=says) as e:
        read_mesh(path)
    assert "\n" not in str(e.value)


def test_a_tileset_input_needs_a_crs_and_no_offset(tmp_path, tiny_export):
    from storage.workdir.layout import campus_frame, read_campus
    from tasks.config import CampusConfig
    from tasks.scan import mesh_placement, place_mesh

    work, _ = tiny_export
    ts = work / "output" / "tileset.json"
    base = {"mesh": [str(ts)], "points": ["p.las"]}
    with pytest.raises(InputError, match="set inputs.crs"):
        mesh_placement(ts, CampusConfig.model_validate({"inputs": base}))
    with pytest.raises(InputError, match="remove inputs.mesh_offset"):
        mesh_placement(ts, CampusConfig.model_validate({"inputs": base | {"crs": "EPSG:32650",
                                                                          "mesh_offset": [1, 2, 3]}}))
    crs = campus_frame(read_campus(WorkDir(work))).crs
    place = mesh_placement(ts, CampusConfig.model_validate({"inputs": base | {"crs": crs}}))
    assert place.ecef and place.to_json()["ecef"] is True
    mesh = place_mesh(read_mesh(ts, offset=place.offset), place, ts)
    truth, _, _ = _merged_world(work)
    assert np.abs(mesh.vertices.min(axis=0) - truth.min(axis=0)).max() < 1e-3


def test_embedded_textures_stay_resolvable(tiny_export, tmp_path, monkeypatch):
    """The tileset's embedded images are referenced as <content.glb>#imageK; readable() writes each to a PNG
    in the input cache (once), with the same pixels; input_exists() checks the container."""
    from PIL import Image

    from storage.formats.embedded import resolve_ref as readable
    from storage.inputs.location import split_embedded
    from storage.inputs.remote import input_exists

    monkeypatch.setenv("MS3D_CACHE", str(tmp_path / "cache"))
    work, _ = tiny_export
    mesh = read_mesh(work / "output" / "tileset.json")
    assert mesh.textures, "the tiny export embeds textures"
    ref = mesh.textures[0]
    assert split_embedded(ref) is not None and input_exists(ref)
    png = readable(ref)
    assert png.endswith(".png") and str(tmp_path / "cache") in png
    from storage.formats.gltf import read_gltf

    pixels = read_gltf(Path(split_embedded(ref)[0])).embedded_textures[ref]
    np.testing.assert_array_equal(np.asarray(Image.open(png).convert("RGB")), pixels)
    assert readable(ref) == png  # written once
    assert not input_exists(str(tmp_path / "gone.glb") + "#image0")
