"""Round trips and bad-input errors of storage.formats.meshes, on small meshes built here."""

from __future__ import annotations

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.meshes import (
    MeshData,
    count_nonmanifold_edges,
    iter_meshes,
    read_mesh,
    read_mesh_dir,
    texture_image,
    write_obj,
    write_ply,
)

ORIGIN = np.array([500_000.0, 4_000_000.0, 50.0])


def grid_mesh(nx: int = 6, ny: int = 5, seed: int = 0):
    """A bumpy (nx x ny) vertex grid, 2 triangles per cell, around UTM-like ORIGIN, on a 0.1 mm lattice."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.arange(nx) * 1.5, np.arange(ny) * 1.25, indexing="xy")
    z = rng.integers(0, 20_000, size=x.shape) / 10_000.0
    vertices = ORIGIN + np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    vertices[:, :2] += rng.integers(-1000, 1000, size=(len(vertices), 2)) / 10_000.0
    i = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([i, i + 1, i + nx + 1], 1), np.stack([i, i + nx + 1, i + nx], 1)])
    return vertices, faces.astype(np.int64)


def images():
    red = np.zeros((16, 8, 3), np.uint8)
    red[..., 0] = 200
    red[0, 0] = (1, 2, 3)
    green = np.zeros((8, 8, 3), np.uint8)
    green[..., 1] = 180
    return [red, green]


def test_obj_round_trip_with_two_textured_materials(tmp_path):
    vertices, faces = grid_mesh()
    m = len(faces)
    rng = np.random.default_rng(1)
    uv = rng.uniform(0, 1, size=(m, 3, 2)).astype(np.float32)
    face_texture = (np.arange(m) % 3 == 0).astype(np.int64)  # interleaved materials
    path = write_obj(
        tmp_path / "model.obj", vertices, faces, uv=uv, texture_images=images(), face_texture=face_texture
    )
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "model.mtl",
        "model.obj",
        "model_tex0.png",
        "model_tex1.png",
    ]

    mesh = read_mesh(path)
    assert mesh.n_faces == m and mesh.n_degenerate_dropped == 0 and mesh.n_duplicate_dropped == 0
    assert mesh.vertices.dtype == np.float64 and mesh.faces.dtype == np.int64
    assert np.abs(mesh.vertices[mesh.faces] - vertices[faces]).max() < 1e-3
    np.testing.assert_array_equal(mesh.faces, faces)  # file order, no seam splitting
    np.testing.assert_allclose(mesh.uv, uv, atol=1e-6)
    assert mesh.uv.dtype == np.float32 and mesh.face_texture.dtype == np.int16
    assert [p.rsplit("/", 1)[-1] for p in mesh.textures] == ["model_tex0.png", "model_tex1.png"]
    np.testing.assert_array_equal(mesh.face_texture, face_texture)
    np.testing.assert_array_equal(texture_image(mesh, 0), images()[0])
    assert mesh.source == str(path)


def test_obj_with_offset_stores_local_coordinates(tmp_path):
    vertices, faces = grid_mesh()
    path = write_obj(tmp_path / "local.obj", vertices, faces, offset=ORIGIN)
    first_v = next(line for line in path.read_text().splitlines() if line.startswith("v "))
    assert float(first_v.split()[1]) < 100  # local, not 500000
    mesh = read_mesh(path, offset=ORIGIN)
    assert np.abs(mesh.vertices - vertices).max() < 1e-6
    mesh_mm = read_mesh(path, offset=ORIGIN * 1000, units_scale=1000.0)  # millimetre files
    assert np.abs(mesh_mm.vertices - vertices * 1000).max() < 1e-3


def test_obj_face_colours_quads_and_negative_indices(tmp_path):
    colours = np.array([[255, 0, 0], [0, 0, 255], [255, 0, 0]], np.uint8)
    vertices, faces = grid_mesh(3, 2)
    write_obj(tmp_path / "c.obj", vertices, faces[:3], face_colors=colours)
    np.testing.assert_array_equal(read_mesh(tmp_path / "c.obj").face_colors, colours)

    (tmp_path / "quad.obj").write_text("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf -4 -3 -2 -1\n")
    quad = read_mesh(tmp_path / "quad.obj")
    np.testing.assert_array_equal(quad.faces, [[0, 1, 2], [0, 2, 3]])
    assert quad.uv is None and quad.face_texture is None


def test_degenerate_and_duplicate_faces_are_dropped_and_counted(tmp_path):
    vertices, faces = grid_mesh(4, 3)  # 12 faces
    bad = faces[:10].copy()
    bad[2] = [bad[2, 0], bad[2, 0], bad[2, 1]]  # repeated vertex id
    bad[5] = [0, 1, 2]  # three collinear grid vertices (same row): zero area
    vertices[2] = vertices[0] + 2.0 * (vertices[1] - vertices[0])  # make row 0 exactly collinear
    bad[8] = [bad[8, 0], bad[8, 1], bad[8, 1]]
    path = write_ply(tmp_path / "d.ply", vertices, np.concatenate([bad, bad[:1][:, ::-1]]))
    mesh = read_mesh(path)
    assert mesh.n_faces == 7 and mesh.n_degenerate_dropped == 3 and mesh.n_duplicate_dropped == 1
    kept = np.delete(bad, [2, 5, 8], axis=0)
    np.testing.assert_array_equal(mesh.faces, kept)


def test_nonmanifold_edges_are_counted_not_dropped():
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [2, 3, 4]])
    assert count_nonmanifold_edges(faces) == 1


def test_ply_round_trip_keeps_float64_world_coordinates(tmp_path):
    vertices, faces = grid_mesh()
    colours = np.random.default_rng(3).integers(0, 256, size=(len(faces), 3)).astype(np.uint8)
    path = write_ply(tmp_path / "truth.ply", vertices, faces, face_colors=colours)
    mesh = read_mesh(path)
    np.testing.assert_array_equal(mesh.vertices, vertices)  # exact: stored as double
    np.testing.assert_array_equal(mesh.faces, faces)
    np.testing.assert_array_equal(mesh.face_colors, colours)
    vcol = np.full((len(vertices), 3), 7, np.uint8)
    np.testing.assert_array_equal(
        read_mesh(write_ply(tmp_path / "v.ply", vertices, faces, vertex_colors=vcol)).vertex_colors, vcol
    )


def test_glb_round_trip_through_trimesh_export(tmp_path):
    import trimesh
    from PIL import Image

    parts = []
    for k, img in enumerate(images()):
        vertices, faces = grid_mesh(4 + k, 3, seed=k)
        local = vertices - ORIGIN  # glTF stores float32: keep it local, add the origin on reading
        uv = np.random.default_rng(k).uniform(0, 1, size=(len(local), 2))
        material = trimesh.visual.material.SimpleMaterial(image=Image.fromarray(img))
        visual = trimesh.visual.TextureVisuals(uv=uv, material=material)
        y_up = np.stack([local[:, 0], local[:, 2], -local[:, 1]], axis=1)  # trimesh writes what it is given
        parts.append((local, faces, uv, trimesh.Trimesh(y_up, faces, visual=visual, process=False)))
    path = tmp_path / "model.glb"
    trimesh.Scene([p[3] for p in parts]).export(path)

    mesh = read_mesh(path, offset=ORIGIN)
    assert mesh.n_faces == sum(len(p[1]) for p in parts)
    assert len(mesh.textures) == 2 and all("#image" in t for t in mesh.textures)
    for k, (local, faces, uv, _) in enumerate(parts):
        sel = mesh.face_texture == mesh.face_texture[0 if k == 0 else -1]
        got = mesh.vertices[mesh.faces[sel]]
        want = (local + ORIGIN)[faces]
        assert got.shape == want.shape and np.abs(got - want).max() < 1e-3
        np.testing.assert_allclose(mesh.uv[sel], uv[faces], atol=1e-6)
        np.testing.assert_array_equal(texture_image(mesh, int(mesh.face_texture[sel][0])), images()[k])


def test_contextcapture_folder_of_tiles(tmp_path):
    for k, (ix, iy) in enumerate([(0, 0), (1, 0)]):
        name = f"Tile_+{ix:03d}_+{iy:03d}"
        vertices, faces = grid_mesh(3 + k, 3, seed=k)
        uv = np.full((len(faces), 3, 2), 0.5, np.float32)
        write_obj(
            tmp_path / "Data" / name / f"{name}.obj",
            vertices,
            faces,
            uv=uv,
            texture_images=images()[k : k + 1],
        )
    tiles = list(iter_meshes(tmp_path / "Data"))
    assert [len(t.faces) for t in tiles] == [8, 12]
    merged = read_mesh_dir(tmp_path / "Data")
    assert merged.n_faces == 20 and len(merged.textures) == 2
    np.testing.assert_array_equal(merged.face_texture, [0] * 8 + [1] * 12)
    np.testing.assert_array_equal(merged.faces[8:], tiles[1].faces + len(tiles[0].vertices))
    assert read_mesh(tmp_path / "Data").n_faces == 20


def test_meshes_with_nothing_usable_raise_input_errors_naming_the_file(tmp_path):
    vertices, faces = grid_mesh(3, 3)
    nan = vertices.copy()
    nan[:] = np.nan
    with pytest.raises(InputError, match="no usable face: of 8 faces 8 touch NaN") as err:
        read_mesh(write_ply(tmp_path / "nan.ply", nan, faces))
    assert "nan.ply" in str(err.value) and "9 of 9 vertices" in str(err.value)
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n")
    with pytest.raises(InputError, match=r"1 touch NaN or infinite vertices \(1 of 3 vertices\)"):
        read_mesh(tmp_path / "nan.obj")

    (tmp_path / "range.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\nf 1 2 9\n")
    with pytest.raises(InputError, match="out of range") as err:
        read_mesh(tmp_path / "range.obj")
    assert "range.obj" in str(err.value) and "2 index vertices out of range" in str(err.value)
    (tmp_path / "empty.obj").write_text("# nothing\nv 0 0 0\n")
    with pytest.raises(InputError, match="no faces"):
        read_mesh(tmp_path / "empty.obj")
    with pytest.raises(InputError, match="not found"):
        read_mesh(tmp_path / "missing.obj")
    (tmp_path / "m.stl").write_text("solid")
    with pytest.raises(InputError, match=r"supported: \.3mx, \.3mxb, \.glb, \.gltf, \.json, \.obj, \.ply"):
        read_mesh(tmp_path / "m.stl")


def test_truncated_or_corrupt_glb(tmp_path):
    import trimesh

    vertices, faces = grid_mesh()
    good = tmp_path / "good.glb"
    trimesh.Trimesh(vertices - ORIGIN, faces, process=False).export(good)
    data = good.read_bytes()
    (tmp_path / "cut.glb").write_bytes(data[: len(data) // 2])
    with pytest.raises(InputError, match="truncated") as err:
        read_mesh(tmp_path / "cut.glb")
    assert "cut.glb" in str(err.value)
    (tmp_path / "junk.glb").write_bytes(data[:12] + b"\xff" * (len(data) - 12))
    with pytest.raises(InputError, match="corrupt") as err:
        read_mesh(tmp_path / "junk.glb")
    assert "junk.glb" in str(err.value)


def test_concat_shifts_indices_and_merges_textures():
    a = MeshData(
        np.eye(3), np.array([[0, 1, 2]]), face_texture=np.array([0], np.int16), textures=["/t/a.png"]
    )
    b = MeshData(
        np.eye(3) + 1, np.array([[2, 1, 0]]), face_texture=np.array([0], np.int16), textures=["/t/a.png"]
    )
    c = MeshData(np.eye(3) + 2, np.array([[0, 2, 1]]))
    m = MeshData.concat([a, b, c])
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [5, 4, 3], [6, 8, 7]])
    np.testing.assert_array_equal(m.face_texture, [0, 0, -1])
    assert m.textures == ["/t/a.png"]


@pytest.mark.parametrize(
    "face_lines",
    [
        "f 1//1 2//1 3//1\r\nf 1//1 3//1 4//1\r\n",  # v//vn, CRLF
        "f\t1/1/1 2/2/1 3/3/1  \nf 1/1/1 3/3/1 4/4/1\n",  # v/vt/vn, tab and trailing spaces
        "f 1/1 2/2 3/3 4/4\n",  # a quad, fan-triangulated
        "f -4/-4 -3/-3 -2/-2\nf -4/-4 -2/-2 -1/-1\n",  # relative ids
    ],
)
def test_obj_face_layouts(tmp_path, face_lines):
    head = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\n"
    (tmp_path / "f.obj").write_bytes((head + face_lines).encode())
    mesh = read_mesh(tmp_path / "f.obj")
    np.testing.assert_array_equal(mesh.faces, [[0, 1, 2], [0, 2, 3]])
    if "/" in face_lines and "//" not in face_lines:
        np.testing.assert_array_equal(mesh.uv[1], [[0, 0], [1, 1], [0, 1]])


@pytest.mark.parametrize("text", [
    # block layout as photogrammetry tools write it: the block parser
    "mtllib none.mtl\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nusemtl a\nf 1/1 2/2 3/3\nusemtl b\nf 1/1 3/3 4/2\n",
    # interleaved statements, quads, 'v//vn', negative ids, tabs and comments: line by line
    "v 0 0 0\nv 1 0 0\nv 1 1 0\nvn 0 0 1\nf 1//1 2//1 3//1\nv 0 1 0\nf -4 -2 -1\n# done\n",
    "v\t0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n",
])
def test_obj_block_parser_agrees_with_the_line_parser(tmp_path, text):
    from storage.formats import obj as obj_io
    from storage.formats import obj_statements

    p = tmp_path / "m.obj"
    p.write_text(text.replace("mtllib none.mtl\n", ""))
    fast = obj_statements.fast_statements(p.read_bytes())
    slow = obj_statements.slow_statements(p, p.read_text())
    if fast is not None:
        for name in ("xyzc", "vt", "counts", "raw_v"):
            assert np.array_equal(getattr(fast, name), getattr(slow, name)), name
        assert (fast.raw_vt is None) == (slow.raw_vt is None)
        assert fast.usemtl_names == slow.usemtl_names and fast.faces_before_usemtl == slow.faces_before_usemtl
    m = obj_io.read_obj(p)
    assert len(m.faces) >= 2 and np.isfinite(m.vertices).all()


def test_obj_block_parser_on_a_written_mesh(tmp_path):
    from storage.formats import obj_statements

    rng = np.random.default_rng(0)
    v = rng.random((500, 3)) * 100
    f = rng.integers(0, 500, (900, 3))
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    write_obj(tmp_path / "w.obj", v, f)
    data = (tmp_path / "w.obj").read_bytes()
    fast = obj_statements.fast_statements(data)
    slow = obj_statements.slow_statements(tmp_path / "w.obj", data.decode())
    assert fast is not None and np.array_equal(fast.xyzc, slow.xyzc) and np.array_equal(fast.raw_v, slow.raw_v)
