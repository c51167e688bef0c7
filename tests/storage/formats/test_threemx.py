"""3MX / 3MXB productions with OpenCTM geometry (storage.formats.threemx), written by synth.threemx."""

import json
import struct

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.meshes import mesh_files, read_mesh
from storage.formats.production import production_of
from storage.formats.threemx import read_3mxb, read_ctm, restore_mg1_indices
from storage.inputs.identity import discover
from synth.threemx import write_3mxb, write_ctm, write_production


def _grid_mesh(n: int = 12):
    """A wavy (n x n) grid of 2 (n-1)^2 triangles, 1 m cells, with per-vertex uv."""
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    v = np.c_[x.ravel(), y.ravel(), 0.3 * np.sin(x.ravel()) * np.cos(y.ravel())]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    uv = (v[:, :2] / (n - 1)).astype(np.float32)
    return v, f, uv


def _triangles(v, f) -> np.ndarray:
    """Each face's corners, rotated to start at its smallest corner and sorted: a set of triangles."""
    t = np.asarray(v, np.float64)[f]
    keys = [tuple(map(tuple, np.roll(tri, -int(np.lexsort(tri.T[::-1])[0]), axis=0).round(5))) for tri in t]
    return np.array(sorted(keys))


def _loop_restore(d):
    """The MG1 index restoration, one triangle at a time (the reference)."""
    idx = np.array(d, np.int64)
    for i in range(len(idx)):
        if i:
            idx[i, 0] += idx[i - 1, 0]
        idx[i, 2] += idx[i, 0]
        idx[i, 1] += idx[i - 1, 1] if i and idx[i, 0] == idx[i - 1, 0] else idx[i, 0]
    return idx


def test_mg1_index_restoration_equals_the_sequential_rule():
    rng = np.random.default_rng(3)
    d = np.c_[rng.integers(0, 3, 500), rng.integers(0, 5, 500), rng.integers(0, 9, 500)]
    np.testing.assert_array_equal(restore_mg1_indices(d), _loop_restore(d))


@pytest.mark.parametrize("method", ["RAW", "MG1"])
def test_openctm_round_trip_keeps_every_triangle_and_uv(method):
    v, f, uv = _grid_mesh()
    got_v, got_f, got_uv = read_ctm(write_ctm(v, f, uv, method))
    np.testing.assert_array_equal(_triangles(got_v, got_f), _triangles(v.astype(np.float32), f))
    np.testing.assert_array_equal(got_uv, uv)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])  # MG1 reorders corners but keeps the winding
    got_n = np.cross(got_v[got_f[:, 1]] - got_v[got_f[:, 0]], got_v[got_f[:, 2]] - got_v[got_f[:, 0]])
    assert (np.sort(n[:, 2]) - np.sort(got_n[:, 2]) < 1e-5).all()


def test_production_reads_the_finest_level_once_with_textures_and_its_srs(tmp_path):
    v, f, uv = _grid_mesh()
    tex = np.zeros((32, 32, 3), np.uint8)
    tex[:, :, 1] = 200
    scene = write_production(tmp_path / "prod", v, f, uv, tex, srs="EPSG:32650", origin=(589000.0, 2712000.0, 15.0))
    mesh = read_mesh(scene)
    assert mesh.n_faces == len(f)  # the four leaves, not the coarse root
    np.testing.assert_allclose(_triangles(mesh.vertices, mesh.faces), _triangles(v.astype(np.float32), f), atol=1e-5)
    assert mesh.face_texture is not None and (mesh.face_texture >= 0).all() and len(mesh.textures) == 4
    img = mesh.embedded_textures[mesh.textures[0]]
    assert img.shape == (32, 32, 3) and abs(int(img[..., 1].mean()) - 200) < 8
    prod = production_of(scene)  # the scene places the production: SRS and SRSOrigin
    assert prod.metadata.srs == "EPSG:32650" and prod.metadata.origin == (589000.0, 2712000.0, 15.0)


def test_folder_discovery_takes_the_scene_and_a_bare_tree_its_root(tmp_path):
    v, f, uv = _grid_mesh()
    scene = write_production(tmp_path / "prod", v, f, uv, None, method="RAW")
    found = discover([str(tmp_path / "prod")], [str(scene)])  # any file stands in for the points here
    assert found.meshes == (str(scene.absolute()),)
    assert sum("3MX production" in why for _, why in found.skipped) == 5  # the root and four leaves
    scene.unlink()  # a bare node tree: read from its root node
    assert [p.name for p in mesh_files(tmp_path / "prod")] == ["Root.3mxb"]
    assert read_mesh(tmp_path / "prod" / "Data" / "Root.3mxb").n_faces == len(f)


def test_bad_productions_fail_with_one_line_naming_the_file(tmp_path):
    v, f, uv = _grid_mesh()
    scene = write_production(tmp_path / "p", v, f, uv, None)
    leaf = next((tmp_path / "p" / "Data").glob("Tile_*/*.3mxb"))
    good = leaf.read_bytes()
    leaf.write_bytes(good[:len(good) - 40])  # truncated
    with pytest.raises(InputError, match="truncated") as e:
        read_mesh(scene)
    assert str(leaf.name) in str(e.value) and "\n" not in str(e.value)
    leaf.unlink()  # a missing child
    with pytest.raises(InputError, match="node file not found"):
        read_mesh(scene)
    bad = tmp_path / "x.3mxb"
    write_3mxb(bad, [{"id": "n", "children": [], "resources": ["g"]}],
               [({"type": "geometryBuffer", "format": "ctm", "id": "g"}, write_ctm(v, f, None, "RAW")
                 .replace(b"RAW\0", b"MG2\0", 1))])
    with pytest.raises(InputError, match="'MG2' is not read"):
        read_mesh(bad)
    (tmp_path / "y.3mxb").write_bytes(b"3MXBO" + struct.pack("<I", 5) + b"{oops")
    with pytest.raises(InputError, match="not valid JSON"):
        read_3mxb(tmp_path / "y.3mxb")
    doc = json.loads(scene.read_text())
    doc["layers"][0]["SRS"] = "ENU:48.8,2.3"
    scene.write_text(json.dumps(doc))
    assert production_of(scene).metadata.enu == (48.8, 2.3)  # a local frame, placed into inputs.crs
    doc["layers"][0]["SRS"] = "Local"
    scene.write_text(json.dumps(doc))
    with pytest.raises(InputError, match="unknown SRS 'Local'"):
        production_of(scene)
