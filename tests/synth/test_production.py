"""The synth writes its mesh as a ContextCapture production and its cameras as a COLMAP model: tiles hold every
face once, seams weld by exact position, defects name faces per tile file, and the campus.yaml needs no
mesh_offset."""

from __future__ import annotations

import json

import numpy as np
import yaml

from storage.formats.camera_files import read_cameras
from storage.formats.meshes import mesh_files, read_mesh
from storage.formats.production import finest_lod, production_key, production_of
from storage.inputs.identity import discover
from synth.production import cluster_decimate, split_tiles, write_production
from synth.scene import Mesh
from tasks.ingest.kernels import open_boundary_vertices, vertex_ids, weld_vertex_index


def grid_plane(n: int = 12, size_m: float = 96.0) -> Mesh:
    """An n x n quad grid (2 n^2 triangles) over [0, size_m]^2 at z = 1.3, with irrational-ish coordinates."""
    xs = np.linspace(0.0, size_m, n + 1) + 0.123456789
    x, y = np.meshgrid(xs, xs, indexing="ij")
    v = np.stack([x.ravel(), y.ravel(), np.full(x.size, 1.3)], axis=1)
    q = np.arange(n + 1) * (n + 1)
    a = (q[:-1, None] + np.arange(n)[None, :]).ravel()
    faces = np.concatenate([np.stack([a, a + n + 1, a + 1], 1), np.stack([a + 1, a + n + 1, a + n + 2], 1)])
    m = len(faces)
    return Mesh(v, faces, np.zeros(m, np.uint8), np.full(m, -1, np.int32), np.full((m, 3), 128, np.uint8))


def test_split_tiles_holds_every_face_once():
    mesh = grid_plane()
    tiles = split_tiles(mesh.vertices, mesh.faces, 50.0)
    assert [t.name for t in tiles] == ["Tile_+000_+000", "Tile_+000_+001", "Tile_+001_+000", "Tile_+001_+001"]
    rows = np.concatenate([t.rows for t in tiles])
    assert np.array_equal(np.sort(rows), np.arange(mesh.n_faces))


def test_written_tiles_weld_back_into_the_plane(tmp_path):
    """Read back as ingest does (seam ids of the production key): the only open edges are the plane's outer
    border (4 n), none along the tile seams; without seam ids every seam edge would be open."""
    mesh = grid_plane()
    out = write_production(tmp_path / "mesh", mesh, 50.0, np.random.default_rng(0), lod_tile="Tile_+001_+001")
    files, skipped = finest_lod(sorted(str(p) for p in (tmp_path / "mesh").rglob("*.obj")))
    assert [str(p) for p in mesh_files(tmp_path / "mesh")] == files  # a folder read takes the same files
    assert [p.split("/")[-1] for p, _ in skipped] == ["Tile_+001_+001_L17.obj"]
    assert sorted(p.split("/")[-1] for p in files) == ["Tile_+000_+000.obj", "Tile_+000_+001.obj",
                                                       "Tile_+001_+000.obj", "Tile_+001_+001_L18.obj"]
    key = production_key(tmp_path / "mesh")
    ids, plain = [], []
    for s, f in enumerate(files):
        m = read_mesh(f, offset=(589_000.0, 2_712_000.0, 15.0))
        canon = weld_vertex_index(m.vertices)
        ids.append(vertex_ids(s, m.faces, canon, m.vertices, seam_key=key))
        plain.append(vertex_ids(s, m.faces, canon))

    def n_open(face_ids):
        f = np.concatenate(face_ids)
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        return int((np.unique(e, axis=0, return_counts=True)[1] == 1).sum())

    assert sum(len(f) for f in ids) == mesh.n_faces
    assert n_open(ids) == 4 * 12
    assert n_open(plain) > 4 * 12 + 2 * 12  # each seam edge counted open, twice
    assert set(out) == {"Tile_+000_+000", "Tile_+000_+001", "Tile_+001_+000", "Tile_+001_+001"}


def test_cluster_decimate_is_coarser_and_stays_on_the_plane():
    mesh = grid_plane(n=24)
    v, f = cluster_decimate(mesh.vertices, mesh.faces, 10.0)
    assert 0 < len(f) < mesh.n_faces // 4 and np.allclose(v[:, 2], 1.3)
    assert not open_boundary_vertices(f, np.arange(len(v))).all()


def test_tiny_campus_is_a_production_with_colmap_cameras(tiny_campus):
    cfg = yaml.safe_load((tiny_campus / "campus.yaml").read_text())
    assert "mesh_offset" not in cfg["inputs"] and cfg["inputs"]["mesh"] == ["mesh"]
    found = discover([str(tiny_campus / "mesh")], [str(tiny_campus / "mls")])
    assert [p.split("/mesh/")[1] for p in found.meshes] == ["Data/Tile_+000_+000/Tile_+000_+000.obj",
                                                          "Data/Tile_+001_+000/Tile_+001_+000.obj"]
    prod = production_of(found.meshes[0])
    reg = json.loads((tiny_campus / "truth" / "registration.json").read_text())
    assert prod.metadata.srs == cfg["inputs"]["crs"] and prod.metadata.origin == tuple(reg["frame_origin"])

    cams = read_cameras(tiny_campus / cfg["inputs"]["cameras"])
    assert cams.fmt == "colmap" and len(cams.cameras) > 4
    assert all((tiny_campus / cfg["inputs"]["images"] / c.image).is_file() for c in cams.cameras)
    assert all(not np.any(c.dist) for c in cams.cameras)  # pinhole renders: no distortion claimed
    # the cameras see the campus: the building's truth vertices project into some image in front of them
    from tasks.quality.truth import load_truth

    tv, _, _, _ = load_truth(tiny_campus)
    sample = tv[:: max(1, len(tv) // 2000)]
    seen = np.zeros(len(sample), bool)
    for c in cams.cameras:
        uv, z = c.project(sample)
        seen |= (z > 0.5) & (uv[:, 0] > 0) & (uv[:, 0] < c.width - 1) & (uv[:, 1] > 0) & (uv[:, 1] < c.height - 1)
    assert seen.mean() > 0.2


def test_defect_faces_name_their_tile_files(tiny_campus):
    defects = json.loads((tiny_campus / "truth" / "defects.json").read_text())["defects"]
    assert defects and all("mesh_faces" in d and "faces" not in d for d in defects)
    meshes = {}
    for d in defects:
        for path, faces in d["mesh_faces"].items():
            if path not in meshes:
                meshes[path] = read_mesh(tiny_campus / path)
            assert 0 <= min(faces) and max(faces) < meshes[path].n_faces
    assert sum(len(f) for d in defects for f in d["mesh_faces"].values()) > 0
