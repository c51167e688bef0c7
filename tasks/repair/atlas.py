"""One texture atlas per region: same-view pieces cut out of their images and shelf-packed (§5.3).

A piece is a connected set of faces labelled with one camera; its bounding box in that camera's image
(plus 2 px) is copied into the atlas. When the pieces do not fit in ``max_px``², all are scaled down
by the same factor. uv are per face corner, OBJ convention (origin bottom-left); faces without a view
keep NaN uv.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

NO_VIEW = -1


@dataclass(frozen=True)
class Atlas:
    """image: (H, W, 3) uint8 or None; uv: (m, 3, 2) float32 per corner (OBJ convention, NaN where
    untextured); view: (m,) int64 camera index or NO_VIEW; charts: number of pieces."""

    image: np.ndarray | None
    uv: np.ndarray
    view: np.ndarray
    charts: int


def _components(labels: np.ndarray, adjacency: np.ndarray, m: int) -> np.ndarray:
    """Connected pieces of faces with one (seen) label."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a, b = adjacency[:, 0], adjacency[:, 1]
    ok = (labels[a] == labels[b]) & (labels[a] != NO_VIEW)
    e = adjacency[ok]
    g = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(m, m))
    return connected_components(g, directed=False)[1]


def build_atlas(xyz: np.ndarray, faces: np.ndarray, labels: np.ndarray, cams: list, load_image,
                adjacency: np.ndarray, max_px: int = 4096, pad: int = 2) -> Atlas:
    """Cut each same-view connected piece out of its image and pack the pieces into one atlas.

    labels: (m,) camera index per face or NO_VIEW; cams: the cameras (``tasks.repair.texture.CameraView``: project,
    width, height); load_image(i) -> (H, W, 3) uint8 of camera i.
    Pieces are packed on shelves, tallest first; when they do not fit in max_px², all are scaled down.
    """
    m = len(faces)
    uv = np.full((m, 3, 2), np.nan, np.float32)
    seen = labels != NO_VIEW
    if not seen.any():
        return Atlas(None, uv, labels, 0)
    comp = _components(labels, adjacency, m)
    pieces = []  # (camera, face ids, (m_i, 3, 2) pixel coords, x0, y0, w, h)
    for cid in np.unique(comp[seen]):
        fids = np.flatnonzero((comp == cid) & seen)
        cam_i = int(labels[fids[0]])
        px, _ = cams[cam_i].project(np.asarray(xyz, np.float64)[faces[fids]].reshape(-1, 3))
        px = px.reshape(-1, 3, 2)
        lo = np.floor(px.reshape(-1, 2).min(0)).astype(int) - pad
        hi = np.ceil(px.reshape(-1, 2).max(0)).astype(int) + pad
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, [cams[cam_i].width - 1, cams[cam_i].height - 1])
        pieces.append((cam_i, fids, px, lo[0], lo[1], hi[0] - lo[0] + 1, hi[1] - lo[1] + 1))
    scale = 1.0
    while True:
        placed, W, H = _shelf_pack([(int(np.ceil(p[5] * scale)), int(np.ceil(p[6] * scale))) for p in pieces], max_px)
        if placed is not None:
            break
        scale *= 0.8
    atlas = np.zeros((H, W, 3), np.uint8)
    from PIL import Image

    for (cam_i, fids, px, x0, y0, w, h), (ax, ay) in zip(pieces, placed):
        img = load_image(cam_i)
        crop = img[y0:y0 + h, x0:x0 + w]
        tw, th = int(np.ceil(w * scale)), int(np.ceil(h * scale))
        if (tw, th) != (w, h):
            crop = np.asarray(Image.fromarray(crop).resize((tw, th), Image.BILINEAR))
        atlas[ay:ay + th, ax:ax + tw] = crop[:th, :tw]
        # pixel centre convention: image pixel (u, v) -> atlas (ax + (u - x0 + 0.5) * scale) / W
        au = (ax + (px[..., 0] - x0 + 0.5) * scale) / W
        av = (ay + (px[..., 1] - y0 + 0.5) * scale) / H
        uv[fids, :, 0] = au
        uv[fids, :, 1] = 1.0 - av
    return Atlas(atlas, uv, labels, len(pieces))


def _shelf_pack(sizes: list[tuple[int, int]], max_px: int) -> tuple[list | None, int, int]:
    """Positions of rectangles (w, h) on shelves in the smallest square power-of-two atlas <= max_px."""
    order = sorted(range(len(sizes)), key=lambda i: -sizes[i][1])
    area = sum(w * h for w, h in sizes)
    side = 64
    while side * side < area and side < max_px:
        side *= 2
    while side <= max_px:
        pos = [None] * len(sizes)
        x = y = shelf = 0
        ok = True
        for i in order:
            w, h = sizes[i]
            if w > side:
                ok = False
                break
            if x + w > side:
                x, y, shelf = 0, y + shelf, 0
            if y + h > side:
                ok = False
                break
            pos[i] = (x, y)
            x += w
            shelf = max(shelf, h)
        if ok:
            used_h = max((pos[i][1] + sizes[i][1] for i in range(len(sizes))), default=1)
            return pos, side, int(min(side, max(8, used_h)))
        side *= 2
    return None, 0, 0


