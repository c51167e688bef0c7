"""Colours and texture of one rebuilt region, on arrays: the fallback colour of each rebuilt face (the
original texture at the closest replaced face), the cameras near enough to see it, the occluders between
them (retained faces around the region and MLS-occupied voxels off the rebuilt surface), and the
projective texture (:func:`tasks.repair.texture.texture_mesh`). No I/O here: images and voxels come in
through arguments and callbacks.

Frames and units: campus-local metres (float64).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from tasks.repair.mesh import ClosestPoint, RebuiltMesh
from tasks.repair.texture import CameraView, sample_texture_colors, texture_mesh, voxel_boxes


def fallback_colors(mesh: RebuiltMesh, data, zone_uv: np.ndarray, zone_texture: np.ndarray,
                    load_texture: Callable[[int], np.ndarray | None]) -> np.ndarray:
    """(m, 3) uint8 colour of each rebuilt face: the original texture sampled at the closest point of the
    closest replaced face. data: the region's ``RegionInput``; zone_uv: (mz, 3, 2) float32 per-corner uv
    of its zone faces; zone_texture: (mz,) int64 texture index (-1 none); load_texture(i): image i or None.
    A region that replaces no face (a free surface only) gets the untextured grey of a missing texture."""
    if not len(data.zone_faces):
        return sample_texture_colors(np.zeros((mesh.n_faces, 2)), np.full(mesh.n_faces, -1), load_texture)
    cen = mesh.xyz[mesh.faces].mean(axis=1)
    fid, bary, _ = ClosestPoint(data.xyz, data.zone_faces).query(cen)
    fid = np.maximum(fid, 0)
    uv = np.einsum("kc,kcd->kd", bary, zone_uv[fid].astype(np.float64))
    return sample_texture_colors(uv, zone_texture[fid], load_texture)


def cameras_near(cams: list[CameraView], lo: np.ndarray, hi: np.ndarray, max_distance_m: float) -> list[CameraView]:
    """The cameras whose centre lies within ``max_distance_m`` of the box [lo, hi] ((3,) metres each)."""
    centres = np.stack([c.centre for c in cams])
    gap = np.maximum(np.maximum(lo - centres, centres - hi), 0)
    return [cams[i] for i in np.flatnonzero(np.linalg.norm(gap, axis=1) <= max_distance_m)]


def occluder_box(lo: np.ndarray, hi: np.ndarray, cams: list[CameraView], radius_m: float
                 ) -> tuple[np.ndarray, np.ndarray]:
    """(box_lo, box_hi) (3,) each: only what lies between the region [lo, hi] and its cameras, at most
    ``radius_m`` beyond the region, can hide it."""
    cc = np.stack([c.centre for c in cams]) if cams else np.zeros((0, 3))
    box_lo = np.maximum(np.minimum(lo, cc.min(0)) if len(cc) else lo, lo - radius_m)
    box_hi = np.minimum(np.maximum(hi, cc.max(0)) if len(cc) else hi, hi + radius_m)
    return box_lo, box_hi


RAY_START_M = 0.28  # a visibility ray starts this far at most from its face's centroid (texture_mesh: 3 + 25 cm)


def voxels_between(voxels: np.ndarray, lo: np.ndarray, hi: np.ndarray, cams: list[CameraView], voxel_m: float
                   ) -> np.ndarray:
    """(k,) bool: the occupied voxels that can meet a visibility ray of the region [lo, hi] to one of ``cams``.

    Every ray runs from within ``RAY_START_M`` of a face centroid (inside [lo, hi]) to a camera centre C, so
    it lies within R = half the box's diagonal + RAY_START_M of the segment from the box centre to C (the
    point at t along a ray is (1 - t) p + t C, (1 - t) |p - b| <= R away from (1 - t) b + t C). A voxel
    farther than R + its half-diagonal (+ 1 cm) from every such segment meets no ray: dropping it changes no
    visibility test and spares building it into the scene (most of a small region's box of occluders).
    voxels: (k, 3) float64 centres, campus-local metres."""
    keep = np.zeros(len(voxels), bool)
    if not len(voxels) or not cams:
        return keep
    b = 0.5 * (lo + hi)
    reach = 0.5 * float(np.linalg.norm(hi - lo)) + RAY_START_M + 0.5 * np.sqrt(3.0) * voxel_m + 0.01
    d = np.stack([c.centre for c in cams]) - b  # (c, 3) box centre -> camera
    dd = np.maximum((d * d).sum(1), 1e-12)
    for s in range(0, len(voxels), 16384):  # (chunk, c) at a time
        rel = voxels[s:s + 16384] - b
        proj = rel @ d.T
        t = np.clip(proj / dd, 0.0, 1.0)
        dist2 = (rel * rel).sum(1)[:, None] - 2.0 * t * proj + t * t * dd  # to the nearest point of each segment
        keep[s:s + 16384] = (dist2 <= reach * reach).any(axis=1)
    return keep


def occluder_surface(mesh: RebuiltMesh, data, voxels: np.ndarray, voxel_m: float
                     ) -> tuple[np.ndarray, np.ndarray, int]:
    """The occluders of a region: its context faces plus a box per MLS voxel that lies off the rebuilt and
    retained surface (more than 0.3 m + a voxel's half-diagonal away: the surface itself must not hide itself).

    voxels: (k, 3) float64 occupied voxel centres. Returns ((v, 3) float64 vertices, (f, 3) int64 faces,
    number of voxels kept).
    """
    surf_v = np.concatenate([mesh.xyz, data.xyz])
    surf_f = np.concatenate([mesh.faces, data.context_faces + len(mesh.xyz)])
    if len(voxels):
        dist = ClosestPoint(surf_v, surf_f).query(voxels)[2]
        voxels = voxels[dist > 0.3 + 0.87 * voxel_m]
    bv, bf = voxel_boxes(voxels, voxel_m)
    return np.concatenate([data.xyz, bv]), np.concatenate([data.context_faces, bf + len(data.xyz)]), len(voxels)


def texture_region(mesh: RebuiltMesh, data, cams: list[CameraView], voxels: np.ndarray, tc, colors: np.ndarray,
                   load_image: Callable[[int], np.ndarray]) -> tuple[object, np.ndarray, dict]:
    """Texture a rebuilt mesh from ``cams`` (occluded by :func:`occluder_surface`); textured faces take the
    image colour at their centroid as their fallback colour.

    tc: ``repair.texture`` config; colors: (m, 3) uint8 fallback colours (updated in place); load_image(i):
    (h, w, 3) uint8 image of ``cams[i]``. Returns (atlas, colors, stats).
    """
    occ_v, occ_f, n_vox = occluder_surface(mesh, data, voxels, tc.occluder_voxel_m)
    atlas, st = texture_mesh(mesh.xyz, mesh.faces, cams, load_image, (occ_v, occ_f), tc, colors)
    st["occluder_voxels"] = n_vox
    if atlas.image is not None:
        cen = mesh.xyz[mesh.faces].mean(axis=1)
        for lab in np.unique(atlas.view[atlas.view >= 0]):
            sel = atlas.view == lab
            px, _ = cams[int(lab)].project(cen[sel])
            img = load_image(int(lab))
            x = np.clip(np.round(px[:, 0]).astype(int), 0, img.shape[1] - 1)
            y = np.clip(np.round(px[:, 1]).astype(int), 0, img.shape[0] - 1)
            colors[sel] = img[y, x]
    return atlas, colors, st
