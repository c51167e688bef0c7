"""Zone faces the MLS did not see stay as they are (repair never makes an unseen surface worse).

A region is a set of grid cells, so its zone holds whatever the cells hold: a facade's defect at the top
storey takes the eave and a strip of roof with it. The street scanner never sees that roof. Rebuilding it
from the fused points re-triangulates the input vertices in a 2D chart, which cuts chords across ridges
and folds: measured on a held-out demo campus, roofs lost 0.6 points of F@5cm and their uncovered area
grew by half. :func:`unseen_faces` finds the zone faces no MLS point comes near (its surface samples,
vertices and centroid all farther than ``clear_m`` from every point) and whose vertices the MLS surface
does not cover; :func:`keep_faces` hands them to the retained mesh, so the rebuild stitches to them like to
any border.

A street scanner sees a horizontal surface above its head from below only. The top of a roof slab over an
eave has the eave's soffit 10-40 cm under it: near, parallel, "along the normal", yet the underside of the
slab, not its top. Measured on the demo campus (seed 7), such soffit points made 2.7 % of the roof area
lose its coverage. :func:`overhead_faces` marks the near-horizontal faces well above the region's lowest
scanned point; for them an MLS point under the face is no evidence, nor one beside it that faces sideways
(a fascia or a wall top next to the roof's edge). An overhead face wound upward is a top (:func:`top_faces`):
only a point above it is evidence of it.

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from tasks.geometry.sampling import sample_surface
from tasks.geometry.triangles import face_normals


def overhead_faces(xyz: np.ndarray, faces: np.ndarray, mls: np.ndarray, *, min_height_m: float,
                   min_abs_nz: float = 0.7) -> np.ndarray:
    """(m,) bool: faces (m, 3) int64 into xyz (n, 3) within ~45° of horizontal (|unit normal z| >=
    ``min_abs_nz``, either orientation) whose lowest vertex lies ``min_height_m`` or more above the 1st
    percentile of the MLS points' z (p, 3): surfaces a street scanner can only have seen from below.
    min_height_m <= 0 or no points: none.

    >>> xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 9], [1, 0, 9], [0, 1, 9], [0, 0, 8], [0, 0, 9], [0, 1, 9]], float)
    >>> overhead_faces(xyz, np.array([[0, 1, 2], [3, 4, 5], [6, 7, 8]]), xyz[:3], min_height_m=3).tolist()
    [False, True, False]
    """
    m = len(faces)
    if min_height_m <= 0 or not (m and len(mls)):
        return np.zeros(m, bool)
    tri = xyz[np.asarray(faces, np.int64)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nz = np.abs(n[:, 2]) / np.maximum(np.linalg.norm(n, axis=1), 1e-300)
    return (nz >= min_abs_nz) & (tri[:, :, 2].min(axis=1) >= np.percentile(mls[:, 2], 1) + min_height_m)


def top_faces(xyz: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) bool: faces (m, 3) int64 into xyz (n, 3) whose winding normal points up (z > 0). Meshes are wound
    outward (OBJ/PLY convention, the MVS and city-model exports ms3d reads), so an overhead one is a
    roof's or a slab's top, which a street scanner below never sees; a mesh wound inward makes them
    undersides, and only the weaker rule (points under the face) applies to them.

    >>> top_faces(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2], [0, 2, 1]])).tolist()
    [True, False]
    """
    tri = xyz[np.asarray(faces, np.int64)]
    return np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])[:, 2] > 0


def _not_evidence(q: np.ndarray, pts: np.ndarray, pts_n: np.ndarray | None, up: np.ndarray, floor_m: np.ndarray
                  ) -> np.ndarray:
    """(q, k) bool: points pts (q, k, 3) that say nothing of an overhead surface through q (q, 3) with upward
    unit normal up (q, 3): lower than ``floor_m`` (q,) along it (the underside of the slab: -tol for a face
    of unknown side, +tol for a roof's top, which a scanner below never sees), or off to the side of the
    45° cone above it while facing sideways (normals pts_n (q, k, 3) more than 60° from up: a fascia or a
    wall top beside the roof's edge). Without normals only the first test is made."""
    delta = pts - q[:, None, :]
    off = np.einsum("qkd,qd->qk", delta, up)
    under = off < floor_m[:, None]
    if pts_n is None:
        return under
    lateral = np.sqrt(np.maximum(np.einsum("qkd,qkd->qk", delta, delta) - off**2, 0.0))
    sideways = np.abs(np.einsum("qkd,qd->qk", pts_n, up)) < 0.5
    return under | (sideways & (lateral > np.maximum(off, 0.0)))


def _near_evidence(tree: cKDTree, mls: np.ndarray, mls_n: np.ndarray | None, q: np.ndarray, up: np.ndarray,
                   floor_m: np.ndarray, clear_m: float, k: int = 16) -> np.ndarray:
    """(q,) bool: an MLS point within ``clear_m`` of q (q, 3) among its ``k`` nearest that is evidence of
    q's overhead surface (upward unit normal up (q, 3), floor floor_m (q,)): :func:`_not_evidence`."""
    if not len(q):
        return np.zeros(0, bool)
    d, j = tree.query(q, k=min(k, len(mls)), distance_upper_bound=clear_m)
    d, j = d.reshape(len(q), -1), j.reshape(len(q), -1)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    return (ok & ~_not_evidence(q, mls[jj], None if mls_n is None else mls_n[jj], up, floor_m)).any(axis=1)


def unseen_faces(xyz: np.ndarray, faces: np.ndarray, mls: np.ndarray, covered_vertex: np.ndarray, *,
                 clear_m: float, step_m: float, overhead: np.ndarray | None = None,
                 under_tol_m: float = 0.05, mls_n: np.ndarray | None = None, top: np.ndarray | None = None,
                 tree: cKDTree | None = None) -> np.ndarray:
    """(m,) bool: faces (m, 3) int64 into xyz (n, 3) with no MLS point (p, 3) within ``clear_m`` of their
    vertices, centroid or surface samples (``step_m`` apart), and none of whose vertices is covered
    (covered_vertex: (n,) bool, the MLS surface lies along the vertex normal). clear_m <= 0: none.
    overhead: (m,) bool faces (:func:`overhead_faces`) for which points more than ``under_tol_m`` under the
    face's plane do not count, nor, given the points' normals mls_n (p, 3), points facing sideways beside it
    (``covered_vertex``: pass it computed likewise). top: (m,) bool overhead faces whose winding normal
    points up (a roof's top, never seen from below): only points more than ``under_tol_m`` above count.
    tree: the k-d tree of ``mls`` when the caller has it.

    >>> xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [11, 0, 0], [10, 1, 0]], float)
    >>> f = np.array([[0, 1, 2], [3, 4, 5]])
    >>> unseen_faces(xyz, f, np.array([[0.2, 0.2, 0.1]]), np.zeros(6, bool), clear_m=0.5, step_m=0.25).tolist()
    [False, True]
    """
    m = len(faces)
    if clear_m <= 0 or not m:
        return np.zeros(m, bool)
    faces = np.asarray(faces, np.int64)
    keep = ~covered_vertex[faces].any(axis=1)
    if not len(mls):
        return keep
    oh = np.zeros(m, bool) if overhead is None else np.asarray(overhead, bool)
    tree = tree if tree is not None else cKDTree(mls)
    tri = xyz[faces]
    up = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    up *= np.where(up[:, 2] < 0, -1.0, 1.0)[:, None] / np.maximum(np.linalg.norm(up, axis=1), 1e-300)[:, None]
    floor = np.where(np.zeros(m, bool) if top is None else np.asarray(top, bool), under_tol_m, -under_tol_m)
    near_v = np.isfinite(tree.query(xyz, distance_upper_bound=clear_m)[0])
    keep[~oh] &= ~near_v[faces[~oh]].any(axis=1)
    cen = tri.mean(axis=1)
    keep[~oh] &= ~np.isfinite(tree.query(cen[~oh], distance_upper_bound=clear_m)[0])
    f_oh = np.flatnonzero(oh & keep)
    if len(f_oh):  # overhead faces: points under them or beside them facing sideways do not count
        q = np.concatenate([tri[f_oh].reshape(-1, 3), cen[f_oh]])
        hit = _near_evidence(tree, mls, mls_n, q, np.concatenate([np.repeat(up[f_oh], 3, axis=0), up[f_oh]]),
                             np.r_[np.repeat(floor[f_oh], 3), floor[f_oh]], clear_m)
        keep[f_oh] &= ~(hit[: 3 * len(f_oh)].reshape(-1, 3).any(axis=1) | hit[3 * len(f_oh):])
    if step_m > 0 and keep.any():
        s, fid = sample_surface(xyz, faces, spacing_m=step_m, rng=0, face_mask=keep)
        if len(s):
            hit = np.isfinite(tree.query(s, distance_upper_bound=clear_m)[0])
            so = oh[fid] & hit
            if so.any():
                hit[so] = _near_evidence(tree, mls, mls_n, s[so], up[fid[so]], floor[fid[so]], clear_m)
            keep[fid[hit]] = False
    return keep


def covered_along_normal(xyz: np.ndarray, normals: np.ndarray, pts: np.ndarray, pts_n: np.ndarray, *,
                         depth_m: float, lateral_m: float, min_cos: float = 0.5, overhead: np.ndarray | None = None,
                         under_tol_m: float = 0.05, top: np.ndarray | None = None, tree: cKDTree | None = None
                         ) -> np.ndarray:
    """(n,) bool: vertices (n, 3) whose nearest MLS point (p, 3) lies within ``depth_m`` with the foot of
    the perpendicular on the scanned surface (lateral offset <= ``lateral_m`` in the point's tangent plane)
    and the point's normal (p, 3) within 60° of the vertex normal (n, 3) (|cos| >= ``min_cos``): the MLS
    surface lies along the vertex normal, in front or behind. A roof vertex above a scanned wall top is not
    covered (the wall faces the street, the roof the sky); a facade 1 m off its scan is. overhead: (n,) bool
    vertices (of :func:`overhead_faces`) that a point more than ``under_tol_m`` below does not cover (a
    soffit under a roof's top); top: (n,) bool overhead vertices of a roof's top (:func:`top_faces`) that
    only a point more than ``under_tol_m`` above covers. tree: the k-d tree of ``pts`` when the caller has it."""
    if not (len(pts) and len(xyz)):
        return np.zeros(len(xyz), bool)
    d, j = (tree if tree is not None else cKDTree(pts)).query(xyz, distance_upper_bound=depth_m)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    delta = xyz - pts[jj]
    off = np.einsum("ij,ij->i", delta, pts_n[jj])
    lat = np.linalg.norm(delta - off[:, None] * pts_n[jj], axis=1)
    agree = np.abs(np.einsum("ij,ij->i", normals, pts_n[jj])) >= min_cos
    out = ok & (lat <= lateral_m) & agree
    if overhead is not None:
        rise = pts[jj][:, 2] - xyz[:, 2]
        floor = np.where(np.zeros(len(xyz), bool) if top is None else np.asarray(top, bool), under_tol_m, -under_tol_m)
        out &= ~(np.asarray(overhead, bool) & (rise < floor))
    return out


def tidy_keep(xyz: np.ndarray, faces: np.ndarray, keep: np.ndarray, overhead: np.ndarray, min_area_m2: float
              ) -> np.ndarray:
    """``keep`` (m,) bool over faces (m, 3) int64 into xyz (n, 3) without specks: kept pieces (connected
    through shared edges) under ``min_area_m2`` are rebuilt, then pieces left to rebuild under it are kept
    (rebuilding a few faces between kept ones gains nothing and costs a chart each), unless the whole
    rebuild is one such piece with no overhead face (m,) bool. Kept balcony tops and roofs with slivers of
    seen faces between them otherwise cut a zone into a thousand charts (held-out campus 9103: 10 -> 1,048
    charts, 4.7 GB). min_area_m2 <= 0: ``keep`` as it is.

    >>> xyz = np.array([[x, y, 0] for x in range(4) for y in range(2)], float)
    >>> f = np.array([[0, 2, 3], [0, 3, 1], [2, 4, 5], [2, 5, 3], [4, 6, 7], [4, 7, 5]])
    >>> tidy_keep(xyz, f, np.array([1, 0, 1, 1, 1, 1], bool), np.ones(6, bool), 1.0).tolist()
    [True, True, True, True, True, True]
    >>> tidy_keep(xyz, f, np.array([1, 0, 0, 0, 0, 0], bool), np.zeros(6, bool), 1.0).tolist()
    [False, False, False, False, False, False]
    >>> tidy_keep(xyz, f, np.array([1, 1, 1, 1, 1, 0], bool), np.zeros(6, bool), 1.0).tolist()  # 4 hangs on 5 only
    [True, True, True, True, False, False]
    """
    from tasks.repair.chart import face_components

    keep = np.asarray(keep, bool).copy()
    if min_area_m2 <= 0 or not len(faces):
        return keep
    tri = xyz[np.asarray(faces, np.int64)]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    for flag in (True, False):
        idx = np.flatnonzero(keep == flag)
        if not len(idx):
            continue
        comp = face_components(faces[idx], len(xyz))
        small = np.bincount(comp, weights=area[idx])[comp] < min_area_m2
        if not flag and len(np.unique(comp)) == 1 and not overhead[idx].any():
            break  # the whole rebuild is one small piece: it stays a rebuild
        keep[idx[small]] = not flag
    return keep


def keep_faces(data, keep: np.ndarray):
    """``data`` (a RegionInput) with the zone faces ``keep`` (mz,) bool moved to the context (retained)
    faces, their stored normals moved along."""
    if not keep.any():
        return data
    fn = data.face_normals
    if fn is not None:
        mz = len(data.zone_faces)
        fn = np.concatenate([fn[:mz][~keep], fn[mz:], fn[:mz][keep]])
    return replace(data, zone_faces=data.zone_faces[~keep],
                   context_faces=np.concatenate([data.context_faces, data.zone_faces[keep]]), face_normals=fn)


def on_retained(pts: np.ndarray, xyz: np.ndarray, rebuild_faces: np.ndarray, retained_faces: np.ndarray,
                tol_m: float, min_cos: float = 0.9) -> np.ndarray:
    """(k,) bool: points pts (k, 3) that lie on the retained surface and off the one to rebuild.

    xyz: (n, 3) region vertices; rebuild_faces: (m, 3) zone faces left to rebuild; retained_faces: (r, 3)
    context and kept faces. A point is on the retained surface when its foot on it is within ``tol_m``
    and straight along the face's normal (|cos| >= ``min_cos``: a point beyond the rim of a hole, off to
    the side of the retained edge, is not), and every face to rebuild lies more than ``tol_m`` farther.
    Such a point (the MLS seeing a kept roof's top over an eave) explains the kept face; in the rebuild it
    would be mapped onto the nearest chart (the soffit 20 cm under it) and folded into it.

    >>> xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, -0.3], [1, 0, -0.3], [0, 1, -0.3]], float)
    >>> top, soffit = np.array([[0, 1, 2]]), np.array([[3, 4, 5]])
    >>> pts = np.array([[0.2, 0.2, 0.01], [0.2, 0.2, -0.29], [1.3, 0.2, 0.0]])
    >>> on_retained(pts, xyz, soffit, top, 0.1).tolist()
    [True, False, False]
    """
    from tasks.repair.mesh import ClosestPoint

    out = np.zeros(len(pts), bool)
    if tol_m <= 0 or not (len(pts) and len(retained_faces)):
        return out
    fid, bary, d_ret = ClosestPoint(xyz, retained_faces).query(pts)
    idx = np.flatnonzero((fid >= 0) & (d_ret <= tol_m))
    if not len(idx):
        return out
    xyz, faces = np.asarray(xyz, np.float64), retained_faces[fid[idx]]
    delta = pts[idx] - np.einsum("kc,kcd->kd", bary[idx], xyz[faces])
    n = face_normals(xyz, faces)
    dist = np.linalg.norm(delta, axis=1)
    along = (np.abs(np.einsum("kd,kd->k", delta, n)) >= min_cos * dist) | (dist <= 1e-3)
    _, _, d_reb = ClosestPoint(xyz, rebuild_faces).query(pts[idx])
    out[idx] = along & (d_reb > d_ret[idx] + tol_m)
    return out


def expand_replaced(replaced: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(mz,) bool over the original zone faces from ``replaced`` over the zone faces left after
    :func:`keep_faces` (kept faces are never replaced)."""
    out = np.zeros(len(keep), bool)
    out[np.flatnonzero(~keep)] = replaced
    return out


__all__ = ["covered_along_normal", "expand_replaced", "keep_faces", "on_retained", "overhead_faces", "tidy_keep", "top_faces",
           "unseen_faces"]
