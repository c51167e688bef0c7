"""Projective texture mapping of a rebuilt region from the vehicle camera images (§5.3).

The paper maps hand-picked MLS images onto the rebuilt mesh with projective texture mapping (Segal et
al. 1992). Here the choice is automatic and seam-aware:

1. *candidates*: every camera in front of a face, within ``max_distance_m`` and
   ``max_view_angle_deg``, whose image contains the face's three corners;
2. *visibility*: a ray from the face centroid to the camera centre must reach the camera: it is cast
   against the scene (the rebuilt mesh, the retained faces around it and occluders the MLS saw,
   voxelised: trees, cars, fences);
3. *quality*: ``q = cos(angle) (f / distance)²``, the pixels per square metre the view gives the
   face (frontal and near beats oblique and far); the data cost of a view is ``1 - q / q_best``;
4. *seams*: labels minimise data cost + ``seam_weight`` x (adjacent faces with different views), a
   Potts energy minimised by alpha-expansion over s-t min-cuts (PyMaxflow);
5. *atlas*: each connected set of faces with one view is cut out of its image (bounding box + 2 px)
   and packed into one atlas per region (shelf packing); faces no image sees keep the colour of the
   original mesh texture (``face_color``) and have NaN uv.

Frames: campus-local metres; cameras follow OpenCV (x right, y down, z forward; pixel (u, v) = column,
row at pixel centres; radial-tangential lens distortion applied, ``storage.formats.cameras``); atlas uv follow OBJ
(origin bottom-left).
"""

from __future__ import annotations

import numpy as np

from storage.formats.cameras import Camera
from tasks.repair.atlas import NO_VIEW, Atlas, build_atlas
from tasks.repair.chart import edges_of, undirected_key
from tasks.repair.views import select_views, select_views_sparse  # noqa: F401  (select_views: re-exported)

# A view is a storage.formats.cameras.Camera: K, distortion (k1, k2, p1, p2, k3), R world(campus-local)-to-camera,
# t, width, height, image path; its project() applies the OpenCV radial-tangential distortion.
CameraView = Camera


def cameras_to_frame(cams: list[Camera], m: np.ndarray, folder: str | None = None) -> list[Camera]:
    """Cameras moved to the frame X' = m[:3,:3] X + m[:3,3] (m a 4x4 similarity s R_m | b).

    A camera maps X to x_c = R X + t; with X = R_m^T (X' - b) / s the same pixels come from
    R' = R R_m^T and t' = s t - R' b (the depth scales by s, pixels do not change; distortion acts on
    x_c / z_c, so it is kept as is). folder: prefixed to each image path when given.
    """
    a, b = np.asarray(m, np.float64)[:3, :3], np.asarray(m, np.float64)[:3, 3]
    s = np.cbrt(np.linalg.det(a))
    rm = a / s
    out = []
    for c in cams:
        r2 = c.R @ rm.T
        image = f"{folder}/{c.image}" if folder is not None else c.image
        out.append(Camera(image, c.K, r2, s * c.t - r2 @ b, c.width, c.height, c.dist))
    return out


# ------------------------------------------------------------------------------------- view selection

def face_geometry(xyz: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """((m, 3) centroids, (m, 3) unit normals, (m,) areas m²)."""
    tri = np.asarray(xyz, np.float64)[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    a = np.linalg.norm(n, axis=1)
    return tri.mean(axis=1), n / np.maximum(a, 1e-18)[:, None], 0.5 * a


def smooth_face_normals(xyz: np.ndarray, faces: np.ndarray, adjacency: np.ndarray, iterations: int = 4) -> np.ndarray:
    """Face normals averaged with their neighbours' (area-weighted), for view angles: a rebuilt surface of
    small triangles over noisy points has normals that flicker by ~10 deg from face to face."""
    _, n, a = face_geometry(xyz, faces)
    v = n * a[:, None]
    for _ in range(iterations):
        acc = v.copy()
        if len(adjacency):
            np.add.at(acc, adjacency[:, 0], v[adjacency[:, 1]])
            np.add.at(acc, adjacency[:, 1], v[adjacency[:, 0]])
        v = acc
    return v / np.maximum(np.linalg.norm(v, axis=1), 1e-18)[:, None]


def view_quality(xyz: np.ndarray, faces: np.ndarray, cams: list[CameraView], *, max_angle_deg: float,
                 max_distance_m: float, margin_px: float = 2.0, normals: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The candidate views of each face and their quality cos(angle) (f / d)²: (face, camera, q), (k,) each
    (int64, int64, float64), by face then camera. A candidate is in front, not too oblique, near enough, and
    has the face's three corners inside the image. normals: (m, 3) to use for the angle (default the faces'
    own)."""
    cen, nrm, _ = face_geometry(xyz, faces)
    if normals is not None:
        nrm = normals
    cmin = np.cos(np.radians(max_angle_deg))
    tri = np.asarray(xyz, np.float64)[faces]
    fi, ci, qv = [], [], []
    for j, cam in enumerate(cams):
        v = cam.centre - cen
        d = np.linalg.norm(v, axis=1)
        cos = np.einsum("ij,ij->i", v, nrm) / np.maximum(d, 1e-12)
        ok = np.flatnonzero((cos >= cmin) & (d <= max_distance_m))
        if not len(ok):
            continue
        uv, z = cam.project(tri[ok].reshape(-1, 3))  # only the faces that face the camera, near enough
        uv, z = uv.reshape(-1, 3, 2), z.reshape(-1, 3)
        inside = ((z > 0.1) & (uv[..., 0] >= margin_px) & (uv[..., 0] <= cam.width - 1 - margin_px)
                  & (uv[..., 1] >= margin_px) & (uv[..., 1] <= cam.height - 1 - margin_px)).all(axis=1)
        ok = ok[inside]
        q = cos[ok] * (cam.K[0, 0] / d[ok]) ** 2
        ok = ok[q > 0]
        fi.append(ok)
        ci.append(np.full(len(ok), j, np.int64))
        qv.append(q[q > 0])
    if not fi:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    fi, ci, qv = np.concatenate(fi), np.concatenate(ci), np.concatenate(qv)
    order = np.lexsort((ci, fi))
    return fi[order], ci[order], qv[order]


def visible(scene, origins: np.ndarray, targets: np.ndarray, centre: np.ndarray, slack_m: float = 0.05) -> np.ndarray:
    """(k,) bool: nothing in ``scene`` (an open3d RaycastingScene built around ``centre``) lies on the
    segment from each origin to its target (up to slack_m before the target).

    An any-hit query (``test_occlusions``, which stops at the first hit) on rays whose direction spans the
    tested segment, so t in [0, 1] covers it: no closest hit is searched for."""
    import open3d as o3d

    if len(origins) == 0:
        return np.zeros(0, bool)
    d = targets - origins
    ln = np.linalg.norm(d, axis=1)
    span = ln - slack_m
    out = np.ones(len(origins), bool)  # a segment shorter than the slack has nothing to test
    test = span > 0
    if test.any():
        seg = d[test] * (span[test] / np.maximum(ln[test], 1e-12))[:, None]
        rays = np.concatenate([origins[test] - centre, seg], axis=1).astype(np.float32)
        out[test] = ~scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0).numpy().astype(bool)
    return out


def face_adjacency(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(e, 2) int64 pairs of faces sharing an edge."""
    e = edges_of(faces)
    key = undirected_key(e, n_vertices)
    fid = np.repeat(np.arange(len(faces)), 3)
    order = np.argsort(key, kind="stable")
    k, f = key[order], fid[order]
    same = k[1:] == k[:-1]
    return np.c_[f[:-1][same], f[1:][same]]


def _shared_edge_length(xyz: np.ndarray, faces: np.ndarray, adjacency: np.ndarray) -> np.ndarray:
    """(e,) length of the edge each adjacent face pair shares."""
    if len(adjacency) == 0:
        return np.zeros(0)
    fa, fb = faces[adjacency[:, 0]], faces[adjacency[:, 1]]
    common = (fa[:, :, None] == fb[:, None, :]).any(axis=2)  # (e, 3) corners of fa also in fb
    idx = np.argsort(~common, axis=1, kind="stable")[:, :2]
    v = np.take_along_axis(fa, idx, axis=1)
    return np.linalg.norm(np.asarray(xyz, np.float64)[v[:, 0]] - np.asarray(xyz, np.float64)[v[:, 1]], axis=1)


# ------------------------------------------------------------------------------------- fallback colours

def sample_texture_colors(uv: np.ndarray, texture: np.ndarray, load_texture) -> np.ndarray:
    """Colours of points of the original texture: uv (k, 2) OBJ convention, texture (k,) index (-1: none),
    load_texture(i) -> (H, W, 3) uint8 or None. Returns (k, 3) uint8 (200 grey where unknown)."""
    out = np.full((len(uv), 3), 200, np.uint8)
    for t in np.unique(texture[texture >= 0]):
        img = load_texture(int(t))
        if img is None:
            continue
        sel = (texture == t) & np.isfinite(uv).all(1)
        h, w = img.shape[:2]
        x = np.clip((uv[sel, 0] % 1.0) * w, 0, w - 1).astype(int)
        y = np.clip((1.0 - uv[sel, 1] % 1.0) * h, 0, h - 1).astype(int)
        out[sel] = img[y, x]
    return out


# ------------------------------------------------------------------------------------- one region

def voxel_boxes(centres: np.ndarray, size_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned cubes around voxel centres: ((8k, 3) vertices, (12k, 3) faces)."""
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], np.float64) - 0.5
    quads = np.array([[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]])
    tri = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    k = len(centres)
    v = (centres[:, None, :] + corners[None] * size_m).reshape(-1, 3)
    f = (tri[None] + 8 * np.arange(k)[:, None, None]).reshape(-1, 3)
    return v, f


def texture_mesh(xyz: np.ndarray, faces: np.ndarray, cams: list[CameraView], load_image, occluders, cfg,
                 fallback_color: np.ndarray) -> tuple[Atlas, dict]:
    """Choose a view per face and build the region's atlas.

    xyz, faces: the rebuilt mesh; cams: candidate cameras (campus frame); load_image(i) -> image of
    cams[i]; occluders: (vertices, faces) of everything else that can hide a face (retained faces
    around the region, MLS occluder voxels); cfg: ``TextureConfig``; fallback_color: (m, 3) uint8.
    Returns (atlas, stats).
    """
    import open3d as o3d

    m = len(faces)
    stats = {"faces": m, "cameras": len(cams)}
    if m == 0 or not cams:
        return Atlas(None, np.full((m, 3, 2), np.nan, np.float32), np.full(m, NO_VIEW), 0), stats
    adj = face_adjacency(faces, len(xyz))
    nrm = smooth_face_normals(xyz, faces, adj)
    fi, ci, q = view_quality(xyz, faces, cams, max_angle_deg=cfg.max_view_angle_deg,
                             max_distance_m=cfg.max_distance_m, normals=nrm)
    stats["candidates"] = len(fi)
    cen, _, _ = face_geometry(xyz, faces)
    centre = cen.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles((np.asarray(xyz, np.float64) - centre).astype(np.float32), np.asarray(faces, np.uint32))
    ov, of = occluders
    if len(of):
        scene.add_triangles((np.asarray(ov, np.float64) - centre).astype(np.float32), np.asarray(of, np.uint32))
    # start each ray off the surface, 3 cm along the normal and 25 cm towards the camera: the face, its
    # noisy neighbours and the retained ring must not hide it; occluders (fences, cars, trees) stand farther
    targets = np.stack([c.centre for c in cams])[ci]
    ray = targets - cen[fi]
    origins = cen[fi] + 0.03 * nrm[fi] + 0.25 * ray / np.maximum(np.linalg.norm(ray, axis=1), 1e-9)[:, None]
    vis = visible(scene, origins, targets, centre)
    stats["occluded"] = int((~vis).sum())
    fi, ci, q = fi[vis], ci[vis], q[vis]
    best = np.zeros(m)
    np.maximum.at(best, fi, q)
    seen = best > 0
    unseen = np.flatnonzero(~seen)  # 'no view' only for faces no camera sees
    # resolution independent: data cost per unit area, seam cost per unit length (both relative to the mean)
    _, _, area = face_geometry(xyz, faces)
    wa = np.maximum(area / max(area.mean(), 1e-12), 1e-6)
    face = np.concatenate([fi, unseen])
    label = np.concatenate([ci, np.full(len(unseen), len(cams), np.int64)])
    cost = np.concatenate([(1.0 - q / best[fi]) * wa[fi], 0.0 * wa[unseen]])
    shared = _shared_edge_length(xyz, faces, adj)
    lab = select_views_sparse(m, face, label, cost, adj,
                              cfg.seam_weight * shared / max(shared.mean(), 1e-12) if len(adj) else 0.0)
    lab = np.where(lab == len(cams), NO_VIEW, lab)
    stats["seen_faces"] = int(seen.sum())
    stats["views_used"] = len(np.unique(lab[lab != NO_VIEW]))
    stats["seams"] = int((lab[adj[:, 0]] != lab[adj[:, 1]]).sum())
    atlas = build_atlas(xyz, faces, lab, cams, load_image, adj, cfg.max_atlas_px)
    stats["charts"] = atlas.charts
    stats["atlas_px"] = None if atlas.image is None else list(atlas.image.shape[:2])
    return atlas, stats
