"""Textured levels of detail: rasterising charts, painting texels from the closest source point, packing
children's atlases, and the export's textured parents."""

from __future__ import annotations

import json
import shutil

import numpy as np

from tasks.export.bake import BakeSource, bake_lod, dilate, pack_children, paint, rasterize, sample_bilinear
from tasks.export.charts import parameterize
from tasks.export.lod import LodMesh


def _plane(n: int, size_m: float = 4.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n grid of squares (2 triangles each) over [0, size_m]^2 at z 0: (positions, faces)."""
    g = np.linspace(0, size_m, n + 1, dtype=np.float32)
    x, y = np.meshgrid(g, g)
    pos = np.stack([x.ravel(), y.ravel(), np.zeros(x.size, np.float32)], axis=1)
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + 1, i.ravel() + n + 1, i.ravel() + n + 2
    return pos, np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)]).astype(np.int32)


def _lod(pos, faces, grade=None) -> LodMesh:
    m = len(faces)
    return LodMesh(pos, faces, np.full((len(pos), 3), 7, np.uint8), np.zeros(m, np.int8) if grade is None else grade,
                   np.zeros(m, np.int8), np.arange(m, dtype=np.int32))


def _gradient_source() -> BakeSource:
    """The 4 m plane textured by a gradient: red grows with east, green with north (64 px)."""
    pos, faces = _plane(1)
    img = np.zeros((64, 64, 3), np.uint8)
    img[..., 0] = np.arange(64)[None, :] * 4
    img[..., 1] = (63 - np.arange(64))[:, None] * 4  # glTF v runs down: the image's top row is north
    uv = np.stack([pos[:, 0] / 4, 1 - pos[:, 1] / 4], axis=1).astype(np.float32)
    return BakeSource(pos, faces, uv, np.zeros(len(faces), np.int16), np.zeros((len(pos), 3), np.uint8), (img,))


def test_rasterize_covers_a_square_atlas_once_per_texel():
    uv = np.array([[0, 0], [1, 0], [0, 1], [1, 1]], np.float32)
    _, texel, bary = rasterize(uv, np.array([[0, 1, 2], [1, 3, 2]]), 8)
    assert sorted(set(texel.tolist())) == list(range(64))
    assert len(texel) == 64 + 8  # the 8 texel centres on the shared diagonal fall in both triangles
    np.testing.assert_allclose(bary.sum(axis=1), 1.0, atol=1e-6)
    assert (bary >= 0).all()


def test_paint_reads_the_texture_at_the_closest_point_and_vertex_colours_elsewhere():
    src = _gradient_source()
    pts = np.array([[1.0, 3.0, 0.5], [3.0, 1.0, -0.2]], np.float32)  # above / below the plane
    got = paint(pts, src).astype(int)
    expected = sample_bilinear(src.images[0], np.array([[0.25, 0.25], [0.75, 0.75]], np.float32)).astype(int)
    assert np.abs(got - expected).max() <= 1
    assert got[0, 0] < got[1, 0] and got[0, 1] > got[1, 1]  # west / north: less red, more green
    plain = BakeSource(src.positions, src.faces, None, np.full(2, -1, np.int16),
                       np.array([[0, 0, 0], [200, 0, 0], [0, 0, 0], [200, 0, 0]], np.uint8))
    assert paint(np.array([[2.0, 2.0, 0.0]], np.float32), plain)[0].tolist() == [100, 0, 0]


def test_baked_atlas_reproduces_the_source_across_the_decimated_surface():
    src = _gradient_source()
    pos, faces = _plane(6)
    baked = bake_lod(_lod(pos, faces), src, 128)
    assert baked.atlas.shape == (64, 64, 3) and baked.uv.shape == (len(baked.positions), 2)  # atlas_side(72 faces)
    assert baked.n_faces == len(faces) and (baked.region == np.arange(len(faces))).all()  # provenance kept
    rng = np.random.default_rng(1)
    f = rng.integers(0, baked.n_faces, 500)
    w = rng.dirichlet([4, 4, 4], 500)  # inside the faces, away from chart edges
    uv = np.einsum("kj,kjc->kc", w, baked.uv[baked.faces[f]])
    xyz = np.einsum("kj,kjc->kc", w, baked.positions[baked.faces[f]].astype(np.float64))
    got = sample_bilinear(baked.atlas, uv.astype(np.float32)).astype(int)
    truth = paint(xyz.astype(np.float32), src).astype(int)
    assert np.median(np.abs(got - truth)) <= 2
    assert np.percentile(np.abs(got - truth), 99) <= 16  # a texel of ~4 m / 45 px: ~6 levels of the gradient


def test_box_charts_do_not_overlap_and_keep_walls_whole():
    """A closed box (a building block): six charts, one per side, no texel of one chart inside another's."""
    import open3d as o3d

    box = o3d.geometry.TriangleMesh.create_box(10, 6, 4).subdivide_midpoint(2)
    box.merge_close_vertices(1e-6)
    pos, faces = np.asarray(box.vertices, np.float32), np.asarray(box.triangles, np.int32)
    vmap, new_faces, uv = parameterize(pos, faces, 256)
    assert (pos[vmap][new_faces] == pos[faces]).all()  # same faces, same corners
    face, texel, _ = rasterize(uv, new_faces, 256)
    side = np.argmax(np.abs(np.cross(pos[faces[:, 1]] - pos[faces[:, 0]], pos[faces[:, 2]] - pos[faces[:, 0]])), axis=1)
    owner = {}
    for f, t in zip(face.tolist(), texel.tolist()):
        owner.setdefault(t, set()).add((side[f], int(np.sign(pos[faces[f]].mean(axis=0)[side[f]] - [5, 3, 2][side[f]]))))
    assert all(len(o) == 1 for o in owner.values())
    assert len({o.pop() for o in owner.values()}) == 6
    e1, e2 = uv[new_faces[:, 1]] - uv[new_faces[:, 0]], uv[new_faces[:, 2]] - uv[new_faces[:, 0]]
    area = np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]).sum() / 2
    assert area > 0.3  # the charts cover a fair share of the atlas


def test_charts_stay_inside_the_atlas_and_one_texel_charts_collapse_to_their_texel():
    """A wall with a few stray faces turned another way (charts of fewer than MIN_CHART_FACES faces): every
    uv inside [0, 1], each one-texel chart's corners on one texel centre."""
    from tasks.export.charts import MIN_CHART_FACES, chart_faces

    pos, faces = _plane(8, 8.0)  # a floor, +U
    tilted = np.array([[20, 0, 0], [20.5, 0, 0.1], [20, 0, 3]], np.float32)  # a lone face facing -N
    pos = np.concatenate([pos, tilted])
    faces = np.concatenate([faces, [[len(pos) - 3, len(pos) - 2, len(pos) - 1]]]).astype(np.int32)
    label, _ = chart_faces(pos, faces)
    sizes = np.bincount(label)
    assert (sizes < MIN_CHART_FACES).sum() == 1 and sizes[label[-1]] == 1
    vmap, new_faces, uv = parameterize(pos, faces, 64)
    assert uv.min() >= 0 and uv.max() <= 1
    lone = uv[new_faces[-1]] * 64
    assert np.ptp(lone, axis=0).max() == 0 and np.allclose(lone[0] % 1, 0.5)


def test_pack_children_keeps_each_childs_colours_at_its_uvs():
    rng = np.random.default_rng(2)
    parts = []
    for k in range(3):
        pos, faces = _plane(2)
        pos = pos + np.float32([5 * k, 0, 0])
        parts.append(LodMesh(pos, faces, np.zeros((len(pos), 3), np.uint8), np.zeros(8, np.int8), np.zeros(8, np.int8),
                             np.full(8, k, np.int32), uv=rng.random((len(pos), 2)).astype(np.float32),
                             atlas=rng.integers(0, 255, (16, 16, 3), dtype=np.uint8)))
    packed = pack_children(parts)
    assert packed.atlas.shape == (32, 32, 3) and packed.n_faces == 24
    assert packed.region.tolist() == [0] * 8 + [1] * 8 + [2] * 8
    for k, p in enumerate(parts):
        sl = slice(9 * k, 9 * (k + 1))
        np.testing.assert_array_equal(_nearest(packed.atlas, packed.uv[sl]), _nearest(p.atlas, p.uv))


def _nearest(image, uv):
    h, w = image.shape[:2]
    return image[np.clip((uv[:, 1] * h).astype(int), 0, h - 1), np.clip((uv[:, 0] * w).astype(int), 0, w - 1)]


def test_dilate_fills_empty_texels_from_their_neighbours():
    img = np.zeros((4, 4, 3), np.uint8)
    img[1, 1] = 200
    filled = np.zeros((4, 4), bool)
    filled[1, 1] = True
    out = dilate(img, filled, rings=8)
    assert (out == 200).all()


def test_export_parents_are_textured_and_keep_provenance(tiny_merged, tmp_path):
    from tasks.config import ExportConfig
    from tasks.export import run_export
    from tasks.export.gltf import read_glb

    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work)
    run_export(work, ExportConfig(lod_texture_px=128))
    parents = sorted((work / "output" / "content").glob("lod*/*.glb"))
    assert parents
    for glb in parents + [work / "output" / "overview.glb"]:
        doc, _ = read_glb(glb.read_bytes())
        assert len(doc["images"]) == 1, glb
        prims = doc["meshes"][0]["primitives"]
        assert all("TEXCOORD_0" in p["attributes"] for p in prims)
        if glb.name != "overview.glb":
            assert all("EXT_mesh_features" in p["extensions"] for p in prims)
    fps = json.loads((work / "output" / "tileset.fingerprints.json").read_text())["nodes"]
    assert all(r["texture_bytes"] > 0 for k, r in fps.items() if k.startswith("L") and not k.startswith("L0_"))

    plain = tmp_path / "plain"
    shutil.copytree(tiny_merged, plain)
    run_export(plain, ExportConfig(lod_texture_px=0))
    for glb in sorted((plain / "output" / "content").glob("lod*/*.glb")):
        assert "images" not in read_glb(glb.read_bytes())[0]


def test_untextured_leaves_keep_vertex_coloured_lit_parents(tiny_merged, tmp_path):
    """An atlas painted from vertex colours adds nothing and loses the shading (textured primitives are
    unlit): a campus without textures keeps vertex-coloured parents."""
    from dataclasses import replace

    from storage.contracts.tile_mesh import read_tile_mesh, write_tile_mesh
    from tasks.config import ExportConfig
    from tasks.export import run_export
    from tasks.export.gltf import read_glb

    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work)
    for d in sorted((work / "tiles").glob("*/merged.json")):
        tm = read_tile_mesh(d.parent)
        write_tile_mesh(d.parent, replace(tm, textures=[], face_texture=np.full(tm.n_faces, -1, tm.face_texture.dtype)))
    run_export(work, ExportConfig(lod_texture_px=128))
    parents = sorted((work / "output" / "content").glob("lod*/*.glb"))
    assert parents
    for glb in parents + [work / "output" / "overview.glb"]:
        doc, _ = read_glb(glb.read_bytes())
        assert "images" not in doc and all("COLOR_0" in p["attributes"] for p in doc["meshes"][0]["primitives"])


def test_one_untextured_tile_keeps_its_ancestors_textured(tiny_merged, tmp_path):
    """A tile without textures among textured ones (a tile all rebuilt, a tile from another source): its
    vertex colours are painted into the parents' atlases, which stay textured up to the overview."""
    from dataclasses import replace

    from storage.contracts.tile_mesh import read_tile_mesh, write_tile_mesh
    from tasks.config import ExportConfig
    from tasks.export import run_export
    from tasks.export.gltf import read_glb

    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work)
    tile = work / "tiles" / "0_0"
    tm = read_tile_mesh(tile)
    write_tile_mesh(tile, replace(tm, textures=[], face_texture=np.full(tm.n_faces, -1, tm.face_texture.dtype)))
    run_export(work, ExportConfig(lod_texture_px=128))
    assert "images" not in read_glb((work / "output" / "content" / "tiles" / "0_0.glb").read_bytes())[0]
    parents = sorted((work / "output" / "content").glob("lod*/*.glb"))
    assert parents
    for glb in parents + [work / "output" / "overview.glb"]:
        assert len(read_glb(glb.read_bytes())[0]["images"]) == 1, glb
