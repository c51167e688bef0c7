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
row at pixel centres; radial-tangential lens distortion applied, ``storage.cameras``); atlas uv follow OBJ
(origin bottom-left).
"""

from __future__ import annotations

import maxflow
import numpy as np

from storage.cameras import Camera

from tasks.repair.atlas import NO_VIEW, Atlas, build_atlas
from tasks.repair.chart import edges_of, undirected_key


# A view is a storage.cameras.Camera: K, distortion (k1, k2, p1, p2, k3), R world(campus-local)-to-camera,
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
                 max_distance_m: float, margin_px: float = 2.0, normals: np.ndarray | None = None) -> np.ndarray:
    """(m, c) float64 quality cos(angle) (f / d)² of each camera for each face; 0 where not a candidate
    (behind, too oblique, too far, or a corner outside the image). normals: (m, 3) to use for the angle
    (default the faces' own)."""
    cen, nrm, _ = face_geometry(xyz, faces)
    if normals is not None:
        nrm = normals
    q = np.zeros((len(faces), len(cams)))
    cmin = np.cos(np.radians(max_angle_deg))
    tri = np.asarray(xyz, np.float64)[faces].reshape(-1, 3)
    for j, cam in enumerate(cams):
        v = cam.centre - cen
        d = np.linalg.norm(v, axis=1)
        cos = np.einsum("ij,ij->i", v, nrm) / np.maximum(d, 1e-12)
        ok = (cos >= cmin) & (d <= max_distance_m)
        if not ok.any():
            continue
        uv, z = cam.project(tri)
        uv, z = uv.reshape(-1, 3, 2), z.reshape(-1, 3)
        inside = ((z > 0.1) & (uv[..., 0] >= margin_px) & (uv[..., 0] <= cam.width - 1 - margin_px)
                  & (uv[..., 1] >= margin_px) & (uv[..., 1] <= cam.height - 1 - margin_px)).all(axis=1)
        ok &= inside
        f = cam.K[0, 0]
        q[ok, j] = cos[ok] * (f / d[ok]) ** 2
    return q


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


def _add_unary(g, nodes, cost0: np.ndarray, cost1: np.ndarray) -> None:
    """Unary cost of x=0 (source side) and x=1 (sink side)."""
    m = np.minimum(cost0, cost1)
    g.add_grid_tedges(nodes, cost1 - m, cost0 - m)


def _expansion_move(c: np.ndarray, lab: np.ndarray, alpha: int, a: np.ndarray, b: np.ndarray, w: np.ndarray,
                    allowed: np.ndarray) -> np.ndarray:
    """One alpha-expansion move: the labels after the faces that lower the energy most switch to ``alpha``.

    c: (m, L) data costs; lab: (m,) current labels; (a, b): (e,) adjacent face pairs with Potts weights w;
    allowed: (m,) faces that may take ``alpha``. Only faces that may switch (allowed, not already alpha)
    are graph nodes; an edge to a face that keeps its label becomes a unary term of the other end (its
    cost if it keeps vs if it switches), which is exact: the fixed end's variable is 0 in every cut. A
    camera sees a fraction of a region, so most graphs are small."""
    m = len(lab)
    cand = allowed & (lab != alpha)
    nc = int(cand.sum())
    if nc == 0:
        return lab
    node = np.full(m, -1, np.int64)
    node[cand] = np.arange(nc)
    fa, fb = cand[a], cand[b]
    la, lb = lab[a], lab[b]
    e00 = w * (la != lb)
    e01 = w * (la != alpha)  # a keeps, b switches
    e10 = w * (lb != alpha)  # a switches, b keeps
    keep = c[cand, lab[cand]].astype(np.float64)
    switch = c[cand, alpha].astype(np.float64)
    one_a, one_b = fa & ~fb, fb & ~fa  # an edge to a face that keeps: a unary term of its candidate end
    keep += np.bincount(node[a[one_a]], e00[one_a], nc) + np.bincount(node[b[one_b]], e00[one_b], nc)
    switch += np.bincount(node[a[one_a]], e10[one_a], nc) + np.bincount(node[b[one_b]], e01[one_b], nc)
    both = fa & fb
    na, nb = node[a[both]], node[b[both]]
    e00, e01, e10 = e00[both], e01[both], e10[both]
    # E = e00 + (e10 - e00) x_a + (0 - e10) x_b + (e01 + e10 - e00) (1 - x_a) x_b
    switch += np.bincount(na, e10 - e00, nc) + np.bincount(nb, -e10, nc)
    g = maxflow.Graph[float](nc, len(na))
    nodes = g.add_nodes(nc)
    _add_unary(g, nodes, keep, switch)  # x = 1 (sink): switch to alpha; x = 0 (source): keep
    g.add_edges(na.astype(np.int32), nb.astype(np.int32), np.maximum(e01 + e10 - e00, 0), np.zeros(len(na)))
    g.maxflow()
    new = lab.copy()
    new[np.flatnonzero(cand)[g.get_grid_segments(nodes)]] = alpha
    return new


def select_views(cost: np.ndarray, adjacency: np.ndarray, seam_weight, cycles: int = 3) -> np.ndarray:
    """Seam-aware view labels: argmin sum_f cost[f, l_f] + sum_{(f, g) adjacent, l_f != l_g} seam_weight_fg.

    cost: (m, L) float64 data costs, np.inf where a label is not allowed (every face must allow at
    least one: the caller's last column is the 'no view' label). adjacency: (e, 2) face pairs;
    seam_weight: a scalar or (e,) per adjacent pair.
    Alpha-expansion (Boykov, Veksler & Zabih 2001): for each label alpha, one s-t min-cut decides which
    faces switch to alpha; Potts is a metric, so each move is exact. Returns (m,) int64 labels.
    """
    m, nl = cost.shape
    big = 1e9
    c = np.where(np.isfinite(cost), cost, big)
    lab = np.argmin(c, axis=1)
    w = np.broadcast_to(np.asarray(seam_weight, np.float64), (len(adjacency),))
    if len(adjacency) == 0 or not (w > 0).any() or nl == 1:
        return lab
    a, b = adjacency[:, 0], adjacency[:, 1]

    def energy(lb):
        return c[np.arange(m), lb].sum() + w[lb[a] != lb[b]].sum()

    best = energy(lab)
    labels = [int(x) for x in range(nl) if np.isfinite(cost[:, x]).any()]
    for _ in range(cycles):
        improved = False
        for alpha in labels:
            new = _expansion_move(c, lab, alpha, a, b, w, np.isfinite(cost[:, alpha]))
            en = energy(new)
            if en < best - 1e-9:
                best, lab, improved = en, new, True
        if not improved:
            break
    return lab


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
    q = view_quality(xyz, faces, cams, max_angle_deg=cfg.max_view_angle_deg, max_distance_m=cfg.max_distance_m,
                     normals=nrm)
    fi, ci = np.nonzero(q > 0)
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
    q_vis = np.zeros_like(q)
    q_vis[fi[vis], ci[vis]] = q[fi[vis], ci[vis]]
    best = q_vis.max(axis=1)
    cost = np.full((m, len(cams) + 1), np.inf)
    seen = best > 0
    cost[seen, :-1] = np.where(q_vis[seen] > 0, 1.0 - q_vis[seen] / best[seen, None], np.inf)
    cost[:, -1] = np.where(seen, np.inf, 0.0)  # 'no view' only for faces no camera sees
    # resolution independent: data cost per unit area, seam cost per unit length (both relative to the mean)
    _, _, area = face_geometry(xyz, faces)
    wa = np.maximum(area / max(area.mean(), 1e-12), 1e-6)[:, None]
    cost = np.where(np.isfinite(cost), cost * wa, np.inf)
    shared = _shared_edge_length(xyz, faces, adj)
    lab = select_views(cost, adj, cfg.seam_weight * shared / max(shared.mean(), 1e-12) if len(adj) else 0.0)
    lab = np.where(lab == len(cams), NO_VIEW, lab)
    stats["seen_faces"] = int(seen.sum())
    stats["views_used"] = len(np.unique(lab[lab != NO_VIEW]))
    stats["seams"] = int((lab[adj[:, 0]] != lab[adj[:, 1]]).sum())
    atlas = build_atlas(xyz, faces, lab, cams, load_image, adj, cfg.max_atlas_px)
    stats["charts"] = atlas.charts
    stats["atlas_px"] = None if atlas.image is None else list(atlas.image.shape[:2])
    return atlas, stats
