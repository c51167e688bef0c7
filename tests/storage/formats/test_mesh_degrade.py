"""Mesh readers degrade where a user's tool would (missing MTL or texture, NaN vertices, bad indices),
with one warning line naming the file; and glTF is read Y-up -> Z-up through its node transforms."""

from __future__ import annotations

import json
import struct

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.meshes import read_mesh, read_mesh_dir, write_obj, write_ply, y_up_to_z_up

SQUARE = "v 0 0 0 255 0 0\nv 1 0 0 0 255 0\nv 1 1 0 0 0 255\nv 0 1 0 9 9 9\n"


def _grid(n: int = 4):
    """An n x n vertex grid in the z=0 plane, 1 m cells, 2 (n-1)^2 faces."""
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    f = np.concatenate([np.stack([i, i + 1, i + n + 1], 1), np.stack([i, i + n + 1, i + n], 1)])
    return v, f.astype(np.int64)


def _textured_obj(tmp_path, kd: str = ""):
    v, f = _grid()
    path = write_obj(tmp_path / "m.obj", v, f, uv=np.full((len(f), 3, 2), 0.5), texture_images=[np.zeros((4, 4, 3))])
    if kd:
        mtl = tmp_path / "m.mtl"
        mtl.write_text(mtl.read_text().replace("Kd 1 1 1", f"Kd {kd}"))
    return path, v, f


def test_missing_texture_reads_untextured_with_one_warning(tmp_path):
    path, v, f = _textured_obj(tmp_path)
    (tmp_path / "m_tex0.png").unlink()
    mesh = read_mesh(path)
    assert mesh.n_faces == len(f) and mesh.textures == [] and mesh.face_texture is None
    assert mesh.uv is not None  # the UVs are the file's: kept
    (line,) = mesh.warnings
    assert line.startswith(f"{path}: texture image ") and "m_tex0.png" in line and "not found" in line
    assert f"{len(f)} of {len(f)} faces read untextured" in line


def test_missing_texture_keeps_the_material_colour(tmp_path):
    path, _, f = _textured_obj(tmp_path, kd="0 0.5 1")
    (tmp_path / "m_tex0.png").unlink()
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.face_colors, np.tile([0, 128, 255], (len(f), 1)))
    assert len(mesh.warnings) == 1


def test_missing_mtl_reads_the_geometry_with_its_vertex_colours(tmp_path):
    (tmp_path / "c.obj").write_text("mtllib gone.mtl\nusemtl wall\n" + SQUARE + "f 1 2 3\nf 1 3 4\n")
    mesh = read_mesh(tmp_path / "c.obj")
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    assert mesh.face_colors is None and mesh.face_texture is None
    np.testing.assert_array_equal(mesh.vertex_colors[:3], [[255, 0, 0], [0, 255, 0], [0, 0, 255]])
    (line,) = mesh.warnings
    assert line == f"{tmp_path / 'c.obj'}: material library {tmp_path / 'gone.mtl'} (mtllib) not found; 2 of 2 faces read untextured"


def test_a_complete_textured_obj_has_no_warning(tmp_path):
    path, _, f = _textured_obj(tmp_path)
    mesh = read_mesh(path)
    assert mesh.warnings == [] and (mesh.face_texture == 0).all()


@pytest.mark.parametrize("fmt", ["ply", "obj"])
def test_nan_vertices_drop_only_the_faces_they_touch(tmp_path, fmt):
    v, f = _grid()
    v[5] = [np.nan, 1.0, 0.0]  # vertex 5 is used by 6 faces
    touching = (f == 5).any(axis=1)
    if fmt == "ply":
        path = write_ply(tmp_path / "m.ply", v, f)
    else:
        path = tmp_path / "m.obj"
        path.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in v) + "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in f))
    mesh = read_mesh(path, offset=(10.0, 0.0, 0.0))
    np.testing.assert_array_equal(mesh.faces, f[~touching])  # indices are the file's
    assert np.isfinite(mesh.vertices).all() and len(mesh.vertices) == len(v)
    np.testing.assert_array_equal(mesh.vertices[mesh.faces], v[f[~touching]] + [10.0, 0.0, 0.0])
    (line,) = mesh.warnings
    assert line == (f"{path}: dropped 6 of 18 faces: 6 touch NaN or infinite vertices (1 of 16 vertices)")


def test_out_of_range_indices_drop_only_their_faces(tmp_path):
    (tmp_path / "r.obj").write_text(SQUARE + "f 1 2 3\nf 1 3 99\nf 1 3 4\nf -9 1 2\n")
    mesh = read_mesh(tmp_path / "r.obj")
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    (line,) = mesh.warnings
    assert "dropped 2 of 4 faces: 2 index vertices out of range (the mesh has 4 vertices; first bad face #1 = [0, 2, 98])" in line


def test_bad_texture_ids_and_short_faces_keep_the_geometry(tmp_path):
    v, f = _grid(3)
    path = write_obj(tmp_path / "t.obj", v, f, uv=np.full((len(f), 3, 2), 0.5), texture_images=[np.zeros((4, 4, 3))])
    text = path.read_text().replace("f 1/1 2/2 5/3", "f 1/1 2/2 5/999") + "f 1 2\n"
    path.write_text(text)
    mesh = read_mesh(path)
    assert mesh.n_faces == len(f)
    assert (mesh.face_texture == -1).sum() == 1 and (mesh.face_texture == 0).sum() == len(f) - 1
    assert len(mesh.warnings) == 2
    assert "dropped 1 of 9 face statements: fewer than 3 vertices" in mesh.warnings[0]
    assert "1 of 8 faces have texture coordinate ids out of range" in mesh.warnings[1]


def test_a_folder_of_tiles_keeps_each_tiles_warning(tmp_path):
    for name in ("a", "b"):
        (tmp_path / f"{name}.obj").write_text(f"mtllib {name}.mtl\n" + SQUARE + "f 1 2 3\n")
    mesh = read_mesh_dir(tmp_path)
    assert mesh.n_faces == 2 and [w.split(":")[0] for w in mesh.warnings] == [str(tmp_path / "a.obj"), str(tmp_path / "b.obj")]


def test_nothing_usable_is_refused(tmp_path):
    (tmp_path / "n.obj").write_text("mtllib gone.mtl\nv 0 0 nan\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 7\n")
    with pytest.raises(InputError, match="no usable face: of 2 faces 1 touch NaN.* and 1 index vertices out of range"):
        read_mesh(tmp_path / "n.obj")


# --- glTF: Y-up, node transforms -------------------------------------------------------------------


def _glb(doc: dict, binary: bytes) -> bytes:
    """A GLB container (glTF 2.0 binary): header, JSON chunk, BIN chunk, each 4-byte aligned."""
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    binary += b"\0" * (-len(binary) % 4)
    body = struct.pack("<II", len(js), 0x4E4F534A) + js + struct.pack("<II", len(binary), 0x004E4942) + binary
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)


def test_glb_node_hierarchy_of_the_default_scene_then_y_up_to_z_up(tmp_path):
    binary = TRIANGLE.tobytes() + np.array([0, 1, 2], np.uint16).tobytes()
    doc = {
        "asset": {"version": "2.0"}, "scene": 1,
        "scenes": [{"nodes": [2]}, {"nodes": [0]}],  # scene 0 (node 2) is not the default: not read
        "nodes": [
            {"translation": [10, 20, 30], "children": [1]},
            {"rotation": [0, 0, 0.70710678, 0.70710678], "scale": [2, 2, 2], "mesh": 0},  # 90 deg about y-up's z
            {"matrix": [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 100, 0, 0, 1], "mesh": 0},
        ],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
        "buffers": [{"byteLength": len(binary)}],
        "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36}, {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
        "accessors": [
            {"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [1, 1, 0]},
            {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"},
        ],
    }  # fmt: skip
    path = tmp_path / "h.glb"
    path.write_bytes(_glb(doc, binary))
    mesh = read_mesh(path, offset=(1000.0, 0.0, 0.0))
    # Y-up world: (10, 20, 30), (10, 22, 30), (8, 20, 30); Z-up (x, -z, y), plus the offset
    np.testing.assert_allclose(mesh.vertices[mesh.faces[0]], [[1010, -30, 20], [1010, -30, 22], [1008, -30, 20]], atol=1e-5)
    assert mesh.n_faces == 1 and mesh.warnings == []


def test_glb_from_trimesh_with_a_node_transform(tmp_path):
    import trimesh

    v, f = _grid(3)
    v[:, 2] = np.arange(len(v)) * 0.1  # not flat, so a wrong axis shows
    transform = trimesh.transformations.rotation_matrix(0.3, [0, 1, 0])
    transform[:3, 3] = [5.0, -2.0, 7.0]
    scene = trimesh.Scene()
    scene.add_geometry(trimesh.Trimesh(v, f, process=False), node_name="building", transform=transform)
    path = tmp_path / "t.glb"
    scene.export(path)  # trimesh writes the node's matrix and the positions as given (no axis change)
    mesh = read_mesh(path)
    want = y_up_to_z_up(trimesh.transform_points(v, transform))
    np.testing.assert_allclose(mesh.vertices[mesh.faces], want[f], atol=1e-5)
    assert np.abs(mesh.vertices[mesh.faces] - v[f]).max() > 1.0  # the transform was not ignored


def test_gltf_with_a_missing_external_image_reads_untextured_with_one_warning(tmp_path):
    import trimesh
    from PIL import Image

    v, f = _grid(3)
    material = trimesh.visual.material.SimpleMaterial(image=Image.fromarray(np.zeros((4, 4, 3), np.uint8)))
    visual = trimesh.visual.TextureVisuals(uv=np.full((len(v), 2), 0.5), material=material)
    files = trimesh.Scene([trimesh.Trimesh(v, f, visual=visual, process=False)]).export(file_type="gltf")
    for name, data in files.items():
        (tmp_path / name).write_bytes(data)
    doc = json.loads((tmp_path / "model.gltf").read_text())
    assert read_mesh(tmp_path / "model.gltf").warnings == []  # embedded image: fine
    doc["images"] = [{"uri": "facade%20north.png", "mimeType": "image/png"}]
    (tmp_path / "model.gltf").write_text(json.dumps(doc))
    mesh = read_mesh(tmp_path / "model.gltf")
    assert mesh.n_faces == len(f) and mesh.textures == []
    assert mesh.warnings == [f"{tmp_path / 'model.gltf'}: texture image facade%20north.png (glTF images) not found; "
                             f"8 of 8 faces read untextured"]
