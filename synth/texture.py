"""A fragmented texture atlas, like ContextCapture's: every triangle gets its own few pixels.

Two triangles share one square cell of ``cell_px`` pixels (lower-left and upper-right halves, a
one-pixel gap along the diagonal so bilinear sampling does not bleed); cells fill atlases of at
most ``max_side_px`` pixels square, as many atlases as needed. Each triangle's pixels hold its face
colour with a per-face brightness change and blurred per-pixel noise.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

from .scene import Mesh


def bake_atlas(mesh: Mesh, rng: np.random.Generator, cell_px: int = 8, blur_px: float = 1.5,
               max_side_px: int = 8192, noise_rgb: float = 12.0, shade: float = 0.08, band_px: int = 1024
               ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Bake ``mesh.face_color`` into atlases.

    Returns (uv, atlases, atlas_index): uv (m, 3, 2) float32 per-corner texture coordinates in
    [0, 1] of the face's own atlas, OBJ convention (u = x / width, v = 1 - y / height, pixel rows
    from the top); atlases: list of (H, W, 3) uint8 images, H = W <= max_side_px; atlas_index: (m,)
    int32 atlas of each face. blur_px: Gaussian sigma of the pixel noise; noise_rgb: its RMS
    before blurring; shade: RMS of the per-face relative brightness change. Deterministic in rng.
    """
    c = int(cell_px)
    m = mesh.n_faces
    k_max = max_side_px // c
    per_atlas = 2 * k_max * k_max
    n_atlas = max(1, -(-m // per_atlas))
    atlas_index = (np.arange(m) // per_atlas).astype(np.int32)
    local = np.arange(m) - atlas_index.astype(np.int64) * per_atlas
    cell, upper = local // 2, (local % 2).astype(bool)
    sizes = [min(per_atlas, m - a * per_atlas) for a in range(n_atlas)]
    k_of = np.array([max(1, int(np.ceil(np.sqrt(-(-s // 2))))) for s in sizes])
    k = k_of[atlas_index]
    cx, cy = cell % k, cell // k
    g = 0.5  # inset from the cell border, pixels
    lower_tri = np.array([[g, g], [c - g - 1.0, g], [g, c - g - 1.0]])
    upper_tri = np.array([[c - g, c - g], [g + 1.0, c - g], [c - g, g + 1.0]])
    px = np.where(upper[:, None, None], upper_tri, lower_tri) + np.stack([cx, cy], 1)[:, None, :] * c
    side = (k * c).astype(np.float64)
    uv = np.empty((m, 3, 2), np.float32)
    uv[..., 0] = px[..., 0] / side[:, None]
    uv[..., 1] = 1.0 - px[..., 1] / side[:, None]

    rgb = mesh.face_color.astype(np.float32) * (1.0 + shade * rng.standard_normal(m)).astype(np.float32)[:, None]
    tile = np.stack([gaussian_filter(rng.normal(0.0, noise_rgb, (band_px, band_px)), blur_px, mode="wrap")
                     for _ in range(3)], axis=-1).astype(np.float32)
    atlases = []
    for a in range(n_atlas):
        ka, first = int(k_of[a]), a * per_atlas
        H = ka * c
        img = np.empty((H, H, 3), np.uint8)
        x = np.arange(H)
        for y0 in range(0, H, band_px):
            y = np.arange(y0, min(H, y0 + band_px))
            cell_id = (y[:, None] // c) * ka + (x[None, :] // c)
            up = (y[:, None] % c) + (x[None, :] % c) >= c - 1
            f = 2 * cell_id + up
            inside = f < sizes[a]
            col = np.where(inside[..., None], rgb[first + np.minimum(f, sizes[a] - 1)], 128.0)
            col += tile[:len(y), :H] if H <= band_px else np.tile(tile, (1, -(-H // band_px), 1))[:len(y), :H]
            img[y0:y0 + len(y)] = np.clip(col, 0, 255).astype(np.uint8)
        atlases.append(img)
    return uv, atlases, atlas_index
