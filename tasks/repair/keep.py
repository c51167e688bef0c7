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
scanned point; for them an MLS point counts as evidence only when it does not lie under the face.

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from tasks.geometry.sampling import sample_surface


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


def _under(q: np.ndarray, pts: np.ndarray, up: np.ndarray, tol_m: float) -> np.ndarray:
    """(q, k) bool: points pts (q, k, 3) more than ``tol_m`` under the plane through q (q, 3) with upward
    unit normal up (q, 3)."""
    return np.einsum("qkd,qd->qk", pts - q[:, None, :], up) < -tol_m


def _near_not_under(tree: cKDTree, mls: np.ndarray, q: np.ndarray, up: np.ndarray, clear_m: float, tol_m: float,
                    k: int = 16) -> np.ndarray:
    """(q,) bool: an MLS point within ``clear_m`` of q (q, 3) among its ``k`` nearest that is not under q's
    plane (upward unit normal up (q, 3))."""
    if not len(q):
        return np.zeros(0, bool)
    d, j = tree.query(q, k=min(k, len(mls)), distance_upper_bound=clear_m)
    d, j = d.reshape(len(q), -1), j.reshape(len(q), -1)
    ok = np.isfinite(d)
    return (ok & ~_under(q, mls[np.where(ok, j, 0)], up, tol_m)).any(axis=1)


def unseen_faces(xyz: np.ndarray, faces: np.ndarray, mls: np.ndarray, covered_vertex: np.ndarray, *,
                 clear_m: float, step_m: float, overhead: np.ndarray | None = None,
                 under_tol_m: float = 0.05) -> np.ndarray:
    """(m,) bool: faces (m, 3) int64 into xyz (n, 3) with no MLS point (p, 3) within ``clear_m`` of their
    vertices, centroid or surface samples (``step_m`` apart), and none of whose vertices is covered
    (covered_vertex: (n,) bool, the MLS surface lies along the vertex normal). clear_m <= 0: none.
    overhead: (m,) bool faces (:func:`overhead_faces`) for which points more than ``under_tol_m`` under
    the face's plane do not count (nor does ``covered_vertex``: pass it computed likewise).

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
    tree = cKDTree(mls)
    tri = xyz[faces]
    up = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    up *= np.where(up[:, 2] < 0, -1.0, 1.0)[:, None] / np.maximum(np.linalg.norm(up, axis=1), 1e-300)[:, None]
    near_v = np.isfinite(tree.query(xyz, distance_upper_bound=clear_m)[0])
    keep[~oh] &= ~near_v[faces[~oh]].any(axis=1)
    cen = tri.mean(axis=1)
    keep[~oh] &= ~np.isfinite(tree.query(cen[~oh], distance_upper_bound=clear_m)[0])
    f_oh = np.flatnonzero(oh & keep)
    if len(f_oh):  # overhead faces: their vertices and centroid, points under the face's plane do not count
        q = np.concatenate([tri[f_oh].reshape(-1, 3), cen[f_oh]])
        hit = _near_not_under(tree, mls, q, np.concatenate([np.repeat(up[f_oh], 3, axis=0), up[f_oh]]), clear_m,
                              under_tol_m)
        keep[f_oh] &= ~(hit[: 3 * len(f_oh)].reshape(-1, 3).any(axis=1) | hit[3 * len(f_oh):])
    if step_m > 0 and keep.any():
        s, fid = sample_surface(xyz, faces, spacing_m=step_m, rng=0, face_mask=keep)
        if len(s):
            hit = np.isfinite(tree.query(s, distance_upper_bound=clear_m)[0])
            so = oh[fid] & hit
            if so.any():
                hit[so] = _near_not_under(tree, mls, s[so], up[fid[so]], clear_m, under_tol_m)
            keep[fid[hit]] = False
    return keep


def covered_along_normal(xyz: np.ndarray, normals: np.ndarray, pts: np.ndarray, pts_n: np.ndarray, *,
                         depth_m: float, lateral_m: float, min_cos: float = 0.5, overhead: np.ndarray | None = None,
                         under_tol_m: float = 0.05) -> np.ndarray:
    """(n,) bool: vertices (n, 3) whose nearest MLS point (p, 3) lies within ``depth_m`` with the foot of
    the perpendicular on the scanned surface (lateral offset <= ``lateral_m`` in the point's tangent plane)
    and the point's normal (p, 3) within 60° of the vertex normal (n, 3) (|cos| >= ``min_cos``): the MLS
    surface lies along the vertex normal, in front or behind. A roof vertex above a scanned wall top is not
    covered (the wall faces the street, the roof the sky); a facade 1 m off its scan is. overhead: (n,) bool
    vertices (of :func:`overhead_faces`) that a point more than ``under_tol_m`` below does not cover (a
    soffit under a roof's top)."""
    if not (len(pts) and len(xyz)):
        return np.zeros(len(xyz), bool)
    d, j = cKDTree(pts).query(xyz, distance_upper_bound=depth_m)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    delta = xyz - pts[jj]
    off = np.einsum("ij,ij->i", delta, pts_n[jj])
    lat = np.linalg.norm(delta - off[:, None] * pts_n[jj], axis=1)
    agree = np.abs(np.einsum("ij,ij->i", normals, pts_n[jj])) >= min_cos
    out = ok & (lat <= lateral_m) & agree
    if overhead is not None:
        out &= ~(np.asarray(overhead, bool) & (pts[jj][:, 2] - xyz[:, 2] < -under_tol_m))
    return out


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


def expand_replaced(replaced: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """(mz,) bool over the original zone faces from ``replaced`` over the zone faces left after
    :func:`keep_faces` (kept faces are never replaced)."""
    out = np.zeros(len(keep), bool)
    out[np.flatnonzero(~keep)] = replaced
    return out


__all__ = ["covered_along_normal", "expand_replaced", "keep_faces", "overhead_faces", "unseen_faces"]
