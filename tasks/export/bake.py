"""Texture baking for textured levels of detail: a decimated mesh gets its own atlas, painted from the
surface it simplifies.

A node passes up ``decimate(content)``; :func:`bake_lod` re-parameterises that mesh (box-projection charts
packed into one square atlas, :mod:`tasks.export.charts`) and paints every texel from the closest point of the source surface
(the leaf's full-resolution textured mesh, or the parent's textured content): the texel's 3D position
(barycentric on the decimated face, ENU metres) -> the closest source face and its barycentric
coordinates (open3d ray-casting scene) -> that face's texture (bilinear) or, for a vertex-coloured face,
its interpolated vertex colours. Texels no chart covers take the colour of their covered neighbours
(a few rings, so bilinear filtering and mipmaps do not bleed the background into a chart's edge).

Sizes: a passed-up atlas is sized for about ``TEXELS_PER_FACE`` texels per face of its mesh, at most
``lod_texture_px`` square (:func:`atlas_side`); a parent's content packs its (up to four) children's atlases
into a square twice that side (:func:`pack_children`), so texels per metre fall with each level up, as the
geometry's detail does, and no atlas exceeds (2 x lod_texture_px)^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from storage.formats.images import decode_rgb, encode_rgb
from tasks.export.charts import parameterize
from tasks.export.lod import LodMesh, _scene, concat_lods

DILATE_RINGS = 8  # rings of empty texels around the charts filled from their neighbours
CHART_PADDING_PX = 2
TEXELS_PER_FACE = 8  # an atlas is sized for about this many texels per face (fewer: texels coarser than vertices)
PACK_EFFICIENCY = 0.35  # share of a box-chart atlas that charts cover (measured: 0.31-0.41 on decimated demo tiles)


def atlas_side(n_faces: int, max_px: int) -> int:
    """The side (px, a multiple of 4, 64 to ``max_px``) of an atlas for a mesh of ``n_faces``: about
    ``TEXELS_PER_FACE`` covered texels per face.

    >>> atlas_side(1_000_000, 1024), atlas_side(20_000, 1024), atlas_side(10, 1024)
    (1024, 680, 64)
    """
    want = np.sqrt(TEXELS_PER_FACE * n_faces / PACK_EFFICIENCY)
    return int(min(max_px, max(64, 4 * np.ceil(want / 4))))


@dataclass(frozen=True, eq=False)
class BakeSource:
    """A textured surface to paint from. positions: (n, 3) float32 ENU metres; faces: (m, 3) int;
    uv: (n, 2) float32 glTF convention (origin top-left) or None; face_texture: (m,) int index into
    ``images`` (-1: vertex-coloured); colors: (n, 3) uint8 sRGB; images: encoded images (objects with a
    ``data`` attribute: JPEG / PNG bytes) or decoded (H, W, 3) uint8 arrays, decoded one at a time."""

    positions: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None
    face_texture: np.ndarray
    colors: np.ndarray
    images: tuple = ()

    @staticmethod
    def of_lod(lod: LodMesh) -> BakeSource:
        """A LodMesh as a source: its atlas when it has one, else its vertex colours."""
        textured = lod.atlas is not None and lod.uv is not None
        return BakeSource(lod.positions, lod.faces, lod.uv if textured else None,
                          np.full(lod.n_faces, 0 if textured else -1, np.int16), lod.colors,
                          (lod.atlas,) if textured else ())  # fmt: skip


def decode_image(image) -> np.ndarray:
    """(H, W, 3) uint8 pixels of an encoded image (``.data`` bytes) or an array as it is."""
    return image if isinstance(image, np.ndarray) else decode_rgb(image.data)


def encode_jpeg(pixels: np.ndarray, quality: int) -> bytes:
    """JPEG bytes of (H, W, 3) uint8 pixels."""
    return encode_rgb(pixels, "JPEG", quality)


def rasterize(uv: np.ndarray, faces: np.ndarray, size: int, chunk_faces: int = 65_536
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The texels whose centres lie in each face's uv triangle.

    uv: (n, 2) in [0, 1] (u right, v down: texel (x, y) spans [x, x + 1) / size); faces: (m, 3).
    Returns (face (k,) int64, texel (k,) int64 flat index y * size + x, barycentric (k, 3) float32).

    >>> f, t, b = rasterize(np.array([[0, 0], [1, 0], [0, 1]], np.float32), np.array([[0, 1, 2]]), 2)
    >>> t.tolist(), b[0].tolist()
    ([0, 1, 2], [0.5, 0.25, 0.25])
    """
    out_f, out_t, out_b = [], [], []
    for start in range(0, len(faces), chunk_faces):
        fi = np.arange(start, min(start + chunk_faces, len(faces)))
        tri = uv[faces[fi]].astype(np.float64) * size  # (c, 3, 2) texel units
        lo = np.clip(np.floor(tri.min(axis=1) - 0.5), 0, size - 1).astype(np.int64)
        hi = np.clip(np.ceil(tri.max(axis=1) - 0.5), 0, size - 1).astype(np.int64)
        nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
        counts = nx * ny
        face = np.repeat(np.arange(len(fi)), counts)
        local = np.arange(int(counts.sum())) - np.repeat(np.cumsum(counts) - counts, counts)
        x = lo[face, 0] + local % nx[face]
        y = lo[face, 1] + local // nx[face]
        bary = _barycentric(tri[face], np.stack([x + 0.5, y + 0.5], axis=1))
        inside = (bary >= -1e-9).all(axis=1)
        out_f.append(fi[face[inside]])
        out_t.append(y[inside] * size + x[inside])
        out_b.append(bary[inside].astype(np.float32))
    if not out_f:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float32)
    return np.concatenate(out_f), np.concatenate(out_t), np.concatenate(out_b)


def _barycentric(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(k, 3) barycentric coordinates of points p (k, 2) in triangles tri (k, 3, 2); a degenerate
    triangle gives -1 (outside)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    ok = np.abs(den) > 1e-12
    safe = np.where(ok, den, 1.0)
    w1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / safe
    w2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / safe
    out = np.stack([1.0 - w1 - w2, w1, w2], axis=1)
    out[~ok] = -1.0
    return out


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(k, 3) uint8: ``image`` (H, W, 3) uint8 sampled bilinearly at uv (k, 2) (glTF convention, texel
    centres at (i + 0.5) / W), clamped to the edge."""
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0].astype(np.float64) * w - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1].astype(np.float64) * h - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return np.clip(np.rint(top * (1 - fy) + bottom * fy), 0, 255).astype(np.uint8)


def paint(points: np.ndarray, source: BakeSource) -> np.ndarray:
    """(k, 3) uint8 colour of the source surface at its closest point to each of ``points`` (k, 3) ENU."""
    import open3d as o3d

    hit = _scene(source.positions, source.faces).compute_closest_points(
        o3d.core.Tensor(np.ascontiguousarray(points, np.float32)))
    face = hit["primitive_ids"].numpy().astype(np.int64)
    w = hit["primitive_uvs"].numpy().astype(np.float64)  # weights of the face's 2nd and 3rd vertices
    bary = np.stack([1.0 - w[:, 0] - w[:, 1], w[:, 0], w[:, 1]], axis=1)
    corners = source.faces[face]  # (k, 3)
    colors = np.einsum("kj,kjc->kc", bary, source.colors[corners].astype(np.float64))
    out = np.clip(np.rint(colors), 0, 255).astype(np.uint8)
    if source.uv is None or not source.images:
        return out
    tex = source.face_texture[face]
    for t in np.unique(tex[tex >= 0]):
        sel = np.flatnonzero(tex == t)
        uv = np.einsum("kj,kjc->kc", bary[sel], source.uv[corners[sel]].astype(np.float64))
        out[sel] = sample_bilinear(decode_image(source.images[int(t)]), uv)
    return out


def dilate(image: np.ndarray, filled: np.ndarray, rings: int = DILATE_RINGS) -> np.ndarray:
    """``image`` (H, W, 3) uint8 with its unfilled texels (``filled`` (H, W) bool False) given the mean of
    their filled 4-neighbours, ring by ring; what is still empty after ``rings`` takes the mean colour."""
    img = image.astype(np.float32)
    mask = filled.copy()
    for _ in range(rings):
        if mask.all():
            break
        acc = np.zeros_like(img)
        cnt = np.zeros(mask.shape, np.float32)
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            m = np.roll(mask, (dy, dx), axis=(0, 1))
            acc += np.roll(img * mask[..., None], (dy, dx), axis=(0, 1))
            cnt += m
        grow = ~mask & (cnt > 0)
        img[grow] = acc[grow] / cnt[grow][:, None]
        mask = mask | grow
    if not mask.all():
        img[~mask] = img[mask].mean(axis=0) if mask.any() else 128.0
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def bake_lod(mesh: LodMesh, source: BakeSource, max_px: int) -> LodMesh:
    """``mesh`` (welded, ENU) re-parameterised into a square atlas (:func:`atlas_side`, at most ``max_px``)
    painted from ``source``: the same faces and provenance, vertices split at chart seams (their colours
    follow), uv and atlas set."""
    if mesh.n_faces == 0:
        return mesh
    px = atlas_side(mesh.n_faces, max_px)
    vmap, faces, uv = parameterize(mesh.positions, mesh.faces, px, CHART_PADDING_PX)
    positions = mesh.positions[vmap]
    face, texel, bary = rasterize(uv, faces, px)
    # faces no texel centre falls in (one-texel charts, slivers): the texel under their uv centroid, painted
    # at their centroid, where no face covers it
    missed = np.ones(len(faces), bool)
    missed[face] = False
    missed = np.flatnonzero(missed)
    xy = np.clip((uv[faces[missed]].mean(axis=1) * px).astype(np.int64), 0, px - 1)
    extra = xy[:, 1] * px + xy[:, 0]
    covered = np.zeros(px * px, bool)
    covered[texel] = True
    take = ~covered[extra]
    face = np.concatenate([face, missed[take]])
    texel = np.concatenate([texel, extra[take]])
    bary = np.concatenate([bary, np.full((int(take.sum()), 3), 1 / 3, np.float32)])
    corners = positions[faces[face]].astype(np.float64)  # (k, 3, 3)
    points = np.einsum("kj,kjc->kc", bary.astype(np.float64), corners)
    image = np.zeros((px * px, 3), np.uint8)
    filled = np.zeros(px * px, bool)
    image[texel] = paint(points, source)
    filled[texel] = True
    atlas = dilate(image.reshape(px, px, 3), filled.reshape(px, px))
    return LodMesh(positions, faces, mesh.colors[vmap], mesh.grade, mesh.source, mesh.region, uv=uv, atlas=atlas)


def pack_children(parts: list[LodMesh]) -> LodMesh:
    """Up to four textured LodMeshes (square atlases, side at most q) as one: faces concatenated (not
    welded, so each vertex keeps its uv), atlases side by side in a (2 q, 2 q) atlas, each in its quadrant's
    corner as it is (no resampling), uvs moved there; what no atlas fills takes the mean colour (so the
    atlas compresses and mipmaps cleanly)."""
    if not 1 <= len(parts) <= 4 or any(p.atlas is None or p.uv is None for p in parts):
        raise ValueError("pack_children: one to four textured meshes")
    q = max(p.atlas.shape[0] for p in parts)
    mean = np.concatenate([p.atlas.reshape(-1, 3) for p in parts]).mean(axis=0)
    atlas = np.empty((2 * q, 2 * q, 3), np.uint8)
    atlas[:] = np.rint(mean).astype(np.uint8)
    uvs = []
    for i, p in enumerate(parts):
        qy, qx = divmod(i, 2)
        s = p.atlas.shape[0]
        atlas[qy * q:qy * q + s, qx * q:qx * q + s] = p.atlas
        uvs.append((p.uv * np.float32(s) + np.array([qx * q, qy * q], np.float32)) / np.float32(2 * q))
    merged = concat_lods(parts)
    return LodMesh(merged.positions, merged.faces, merged.colors, merged.grade, merged.source, merged.region,
                   uv=np.concatenate(uvs).astype(np.float32), atlas=atlas)

