"""Zone faces the MLS did not see stay as they are (repair never makes an unseen surface worse).

A region is a set of grid cells, so its zone holds whatever the cells hold: a facade's defect at the top
storey takes the eave and a strip of roof with it. The street scanner never sees that roof. Rebuilding it
from the fused points re-triangulates the input vertices in a 2D chart, which cuts chords across ridges
and folds: measured on a held-out demo campus, roofs lost 0.6 points of F@5cm and their uncovered area
grew by half. :func:`unseen_faces` finds the zone faces no MLS point comes near (its surface samples,
vertices and centroid all farther than ``clear_m`` from every point) and whose vertices the MLS surface
does not cover; :func:`keep_faces` hands them to the retained mesh, so the rebuild stitches to them like to
any border.

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from tasks.geometry.sampling import sample_surface


def unseen_faces(xyz: np.ndarray, faces: np.ndarray, mls: np.ndarray, covered_vertex: np.ndarray, *,
                 clear_m: float, step_m: float) -> np.ndarray:
    """(m,) bool: faces (m, 3) int64 into xyz (n, 3) with no MLS point (p, 3) within ``clear_m`` of their
    vertices, centroid or surface samples (``step_m`` apart), and none of whose vertices is covered
    (covered_vertex: (n,) bool, the MLS surface lies along the vertex normal). clear_m <= 0: none.

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
    tree = cKDTree(mls)
    near_v = np.isfinite(tree.query(xyz, distance_upper_bound=clear_m)[0])
    keep &= ~near_v[faces].any(axis=1)
    cen = xyz[faces].mean(axis=1)
    keep &= ~np.isfinite(tree.query(cen, distance_upper_bound=clear_m)[0])
    if step_m > 0 and keep.any():
        s, fid = sample_surface(xyz, faces, spacing_m=step_m, rng=0, face_mask=keep)
        if len(s):
            hit = np.isfinite(tree.query(s, distance_upper_bound=clear_m)[0])
            keep[fid[hit]] = False
    return keep


def covered_along_normal(xyz: np.ndarray, normals: np.ndarray, pts: np.ndarray, pts_n: np.ndarray, *,
                         depth_m: float, lateral_m: float, min_cos: float = 0.5) -> np.ndarray:
    """(n,) bool: vertices (n, 3) whose nearest MLS point (p, 3) lies within ``depth_m`` with the foot of
    the perpendicular on the scanned surface (lateral offset <= ``lateral_m`` in the point's tangent plane)
    and the point's normal (p, 3) within 60° of the vertex normal (n, 3) (|cos| >= ``min_cos``): the MLS
    surface lies along the vertex normal, in front or behind. A roof vertex above a scanned wall top is not
    covered (the wall faces the street, the roof the sky); a facade 1 m off its scan is."""
    if not (len(pts) and len(xyz)):
        return np.zeros(len(xyz), bool)
    d, j = cKDTree(pts).query(xyz, distance_upper_bound=depth_m)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    delta = xyz - pts[jj]
    off = np.einsum("ij,ij->i", delta, pts_n[jj])
    lat = np.linalg.norm(delta - off[:, None] * pts_n[jj], axis=1)
    agree = np.abs(np.einsum("ij,ij->i", normals, pts_n[jj])) >= min_cos
    return ok & (lat <= lateral_m) & agree


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


__all__ = ["covered_along_normal", "expand_replaced", "keep_faces", "unseen_faces"]
