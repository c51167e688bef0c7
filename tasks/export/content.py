"""One node's content, pure: per-face provenance features, bounding boxes, cropped textures, and a merged
tile or a decimated mesh as glTF (y-up) content."""

from __future__ import annotations

import numpy as np

from storage.contracts.tile_mesh import TileMesh
from storage.formats.images import embedded_texture
from tasks.config import ExportConfig
from tasks.export.bake import BakeSource, encode_jpeg
from tasks.export.georef import EnuProjector, enu_to_gltf, gltf_to_enu
from tasks.export.gltf import GltfImage, GltfMesh, split_by_feature
from tasks.export.lod import LodMesh, sample_colors, weld

MIN_HALF_EXTENT_M = 0.01
BOX_PAD_M = 0.001  # bounding boxes grow by this, so lossy (Draco-quantized) positions stay inside


def feature_rows(grade: np.ndarray, source: np.ndarray, region: np.ndarray):
    """One feature per distinct (grade, source, region): (feature per face (m,), grade (k,) int8,
    source (k,) int8, region (k,) int32), features ordered by (region, grade, source).

    >>> f, g, s, r = feature_rows(np.array([0, 1, 0], np.int8), np.array([0, 1, 0], np.int8), np.array([-1, 4, -1]))
    >>> f.tolist(), g.tolist(), s.tolist(), r.tolist()
    ([0, 1, 0], [0, 1], [0, 1], [-1, 4])
    """
    if len(grade) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.int8), np.zeros(0, np.int32)
    key = ((np.asarray(region, np.int64) + 1) << 8) | ((np.asarray(grade, np.int64) + 1) << 2) | np.asarray(source, np.int64)
    rows, inverse = np.unique(key, return_inverse=True)
    return (inverse.reshape(-1), (((rows >> 2) & 0x3F) - 1).astype(np.int8), (rows & 0x3).astype(np.int8),
            ((rows >> 8) - 1).astype(np.int32))


def box_from_bounds(lo, hi) -> list[float]:
    """3D Tiles ``box`` (centre, three half-axes) of the axis-aligned box [lo, hi] (ENU metres), grown by
    ``BOX_PAD_M``."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = (lo + hi) / 2
    h = np.maximum((hi - lo) / 2 + BOX_PAD_M, MIN_HALF_EXTENT_M)
    return [*map(float, c), float(h[0]), 0.0, 0.0, 0.0, float(h[1]), 0.0, 0.0, 0.0, float(h[2])]


def prepare_texture(path: str, uv: np.ndarray, max_px: int, quality: int, multiple_of: int = 1
                    ) -> tuple[GltfImage, np.ndarray, np.ndarray]:
    """An atlas cropped to the pixels ``uv`` (k, 2) (glTF convention) use and downscaled to ``max_px``
    (:func:`storage.formats.images.embedded_texture`): (encoded image, its pixels (H, W, 3) uint8, uv
    remapped to the new image (k, 2) float32)."""
    data, mime, pixels, new_uv = embedded_texture(path, uv, max_px, quality, multiple_of)
    return GltfImage(data, mime), pixels, new_uv


def leaf_content(tm: TileMesh, projector: EnuProjector, cfg: ExportConfig) -> tuple[GltfMesh, LodMesh]:
    """A ground tile's full-resolution content (glTF, y-up) and its vertex-coloured LodMesh (ENU)."""
    # one vertex per (vertex, texture) so each texture's crop can remap its own uvs
    faces, src, group = split_by_feature(tm.faces, tm.face_texture.astype(np.int64) + 1)
    faces = faces.astype(np.int32)  # < 2**31 vertices (glTF indices are uint32); shared by the glTF and the LodMesh
    group -= 1
    enu = projector.local_to_enu(tm.vertices).astype(np.float32)[src]  # float32 first: same bits, half the memory
    uv = np.zeros((len(src), 2), np.float32)
    colors = (tm.vertex_colors[src] if tm.vertex_colors is not None else np.full((len(src), 3), 180, np.uint8)).copy()
    images = []
    order = np.argsort(group, kind="stable")  # the vertices of each texture: one slice of order (no scan per texture)
    sorted_group = group[order]
    used_textures = [int(g) for g in np.unique(sorted_group) if g >= 0]
    starts = np.searchsorted(sorted_group, used_textures, side="left")
    ends = np.searchsorted(sorted_group, used_textures, side="right")
    new_texture = np.full(len(tm.textures) + 1, -1, np.int16)  # old texture + 1 -> its index among the used
    for new_index, (k, a, b) in enumerate(zip(used_textures, starts, ends)):
        sel = order[a:b]
        uv_gltf = np.stack([tm.uv[src[sel], 0], 1.0 - tm.uv[src[sel], 1]], axis=1)
        image, pixels, uv[sel] = prepare_texture(tm.textures[k], uv_gltf, cfg.max_texture_px, cfg.jpeg_quality,
                                                 4 if cfg.texture == "ktx2" else 1)
        colors[sel] = sample_colors(pixels, uv[sel])
        images.append(image)
        new_texture[k + 1] = new_index
    face_texture = new_texture[tm.face_texture.astype(np.int64) + 1]
    del order, sorted_group, group, src
    feature, g_rows, s_rows, r_rows = feature_rows(tm.grade, tm.source, tm.region)
    gltf = GltfMesh(positions=enu_to_gltf(enu), faces=faces, feature=feature, grade=g_rows, source=s_rows,
                    region=r_rows, face_texture=face_texture, uv=uv if images else None, vertex_colors=colors,
                    images=images, face_deviation=tm.face_deviation, face_confidence=tm.face_score)  # fmt: skip
    lod = weld(LodMesh(enu, faces, colors, tm.grade, tm.source, tm.region))
    return gltf, lod


def lod_gltf(lod: LodMesh, jpeg_quality: int = 85) -> GltfMesh:
    """A LodMesh as glTF content (y-up): textured by its atlas (JPEG) when it has one, else vertex-coloured."""
    feature, g_rows, s_rows, r_rows = feature_rows(lod.grade, lod.source, lod.region)
    textured = lod.atlas is not None and lod.uv is not None
    return GltfMesh(positions=enu_to_gltf(lod.positions), faces=lod.faces, feature=feature, grade=g_rows,
                    source=s_rows, region=r_rows, face_texture=np.full(lod.n_faces, 0 if textured else -1, np.int16),
                    uv=lod.uv if textured else None, vertex_colors=lod.colors,
                    images=[GltfImage(encode_jpeg(lod.atlas, jpeg_quality), "image/jpeg")] if textured else [])  # fmt: skip


def bake_source(mesh: GltfMesh) -> BakeSource:
    """A leaf's full-resolution glTF content as the surface its passed-up atlas is painted from (ENU)."""
    colors = mesh.vertex_colors if mesh.vertex_colors is not None else np.full((len(mesh.positions), 3), 180, np.uint8)
    return BakeSource(gltf_to_enu(mesh.positions).astype(np.float32), mesh.faces, mesh.uv, mesh.face_texture, colors, tuple(mesh.images))

