"""The synth generator end to end on the tiny preset: determinism, truth consistency, formats."""

from __future__ import annotations

import json

import numpy as np
import pytest

from storage.formats.points import read_header, read_points
from synth.generate import generate
from synth.tile_meshes import read_production
from tasks.quality.metrics import point_to_mesh_distance
from tasks.quality.truth import load_truth


def _checksums(out):
    return {k: v["sha256"] for k, v in json.loads((out / "truth" / "manifest.json").read_text())["files"].items()}


def test_same_seed_same_bytes_other_seed_differs(tiny_campus, tmp_path):
    again = generate("tiny", seed=1, out=tmp_path / "again")
    assert _checksums(again) == _checksums(tiny_campus)
    other = generate("tiny", seed=2, out=tmp_path / "other")
    a, b = _checksums(tiny_campus), _checksums(other)
    tile = "mesh/Data/Tile_+001_+000/Tile_+001_+000.obj"
    assert a[tile] != b[tile]
    assert a["truth/truth_mesh.ply"] != b["truth/truth_mesh.ply"]
    assert any(a[k] != b.get(k) for k in a if k.startswith("mls/"))


def test_refuses_non_empty_folder(tmp_path):
    (tmp_path / "x.txt").write_text("keep me")
    with pytest.raises(FileExistsError):
        generate("tiny", seed=1, out=tmp_path)
    assert (tmp_path / "x.txt").read_text() == "keep me"


def test_inverse_transform_puts_mls_on_truth(tiny_campus):
    tv, tf, tc, origin = load_truth(tiny_campus)
    reg = json.loads((tiny_campus / "truth" / "registration.json").read_text())
    m = np.asarray(reg["matrix_mls_to_mesh"])
    laz = sorted((tiny_campus / "mls").glob("*.laz"))[0]
    info = read_header(laz)
    assert info.crs == "EPSG:32650" and info.bounds[0, 0] > 500_000  # large projected coordinates
    pc = read_points(laz)
    keep = np.isin(pc.classification, (2, 6, 11))  # ground, building, road: not trees/cars/people
    xyz = pc.xyz[keep][::20] - origin
    on_mesh = xyz @ m[:3, :3].T + m[:3, 3]
    d = point_to_mesh_distance(on_mesh, tv - origin, tf)
    assert np.median(d) < 0.01
    # without the transform the points are far off: the perturbation is real
    assert np.median(point_to_mesh_distance(xyz, tv - origin, tf)) > 0.1


def test_holes_have_no_mvs_faces(tiny_campus):
    defects = json.loads((tiny_campus / "truth" / "defects.json").read_text())["defects"]
    holes = [d for d in defects if "hole" in d["type"]]
    assert holes, "the tiny preset injects holes"
    origin = np.asarray(json.loads((tiny_campus / "truth" / "registration.json").read_text())["frame_origin"])
    mvs, meta_origin = read_production(tiny_campus / "mesh")
    assert np.allclose(meta_origin, origin)
    cent = mvs.vertices[mvs.faces].mean(axis=1) - origin
    from scipy.spatial import cKDTree

    tree = cKDTree(cent)
    for d in holes:
        s = np.asarray(d["samples"])
        # hole samples lie on the true surface inside the hole: no MVS face centroid within 3 cm
        near = tree.query(s, k=1)[0]
        assert np.median(near) > 0.03, d["type"]


def test_no_points_on_roofs_of_tall_buildings(tiny_campus):
    tv, tf, tc, origin = load_truth(tiny_campus)
    scene = json.loads((tiny_campus / "truth" / "scene.json").read_text())
    reg = np.asarray(json.loads((tiny_campus / "truth" / "registration.json").read_text())["matrix_mls_to_mesh"])
    pts = np.concatenate([read_points(p).xyz for p in sorted((tiny_campus / "mls").glob("*.laz"))])[::5] - origin
    pts = pts @ reg[:3, :3].T + reg[:3, 3]
    d, face = point_to_mesh_distance(pts, tv - origin, tf, return_faces=True)
    on = d < 0.05
    roof = tc[face[on]] == 3
    tall = max(b["height_m"] for b in scene["buildings"]) >= 6.0
    assert tall and roof.mean() < 0.005


def test_images_drawn_inline_equal_those_of_the_image_thread(tiny_campus, tmp_path, monkeypatch):
    # the camera images render in a thread beside the rest, drawing from their own random stream: the files
    # must not depend on it
    import synth.generate as gen

    monkeypatch.setattr(gen, "IMAGES_IN_THREAD", False)
    inline = generate("tiny", seed=1, out=tmp_path / "inline")
    a, b = _checksums(inline), _checksums(tiny_campus)
    assert any(k.startswith("images/") for k in a)  # the tiny preset has cameras: the test compares images
    assert a == b
