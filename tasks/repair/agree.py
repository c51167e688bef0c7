"""Zone faces the scan agrees with stay as they are (a repair the evidence does not support is not applied).

A region is rebuilt because its patches were graded bad, but a bad patch is a few square metres and its
defect often a fraction of it: a hole in a facade, a dent, a bridged window. Rebuilding the whole zone
from fused points re-triangulates the input's vertices and the scan in a 2D chart, which cuts chords
across every corner and recess the chart folds over. Measured on a real ContextCapture street corner
(defect case seed 2): of 231 m² rebuilt, 70 m² lay more than 5 cm from the truth, 57 m² of them in the two
hole regions; the roofs beside them lost 0.8 point of F@5cm. A false alarm is worse still: the whole zone
is rebuilt though nothing in it is wrong.

The evidence that a mesh is wrong is scanned surface it does not explain: an MLS point farther than
``gap_m`` from every face of the region (zone and retained ring). Every defect the repair fixes leaves
such points: a hole (the scan inside it), a dent or an offset (the scan in front of or behind the
mesh), a bridged recess (the scan inside the recess, behind the bridge), a melted balcony or a bump (the
wall behind them), a missing thin structure. What real productions hold and the scan agrees with leaves
none, whatever the mesh's topology: open edges at node borders, slivers, texture seams, duplicated
vertices, hidden layers where two nodes overlap (the scan lies on the front one; the mesh -> scan
direction would call the back one a recess, which is why only the scan -> mesh direction is read here).

:func:`agreeing_faces` keeps every zone face farther than ``band_m`` from such points (clusters of at
least ``min_points`` within ``cluster_m``: a stray point, a pedestrian's arm, is no defect); the rest is
rebuilt and stitched to the kept faces like to any retained border. Kept pieces smaller than
``min_area_m2`` are rebuilt (specks would cut the zone into many charts).

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.geometry.sampling import sample_surface
from tasks.geometry.triangles import face_areas


def unexplained_points(pts: np.ndarray, xyz: np.ndarray, faces: np.ndarray, *, gap_m: float, cluster_m: float,
                       min_points: int) -> tuple[np.ndarray, np.ndarray]:
    """((p,) bool, (p,) int64): points pts (p, 3) farther than ``gap_m`` from every face (f, 3) into xyz
    (n, 3) with at least ``min_points`` such points (itself included) within ``cluster_m``, and each
    point's closest face (-1 when there is no face): the face that should have explained it.

    >>> pts = np.array([[0.0, 0, 0.01], [1, 0, 0.3], [2, 0, 0.3], [2.05, 0, 0.3], [2, 0.05, 0.3]])
    >>> xyz = np.array([[-1, -1, 0], [3, -1, 0], [3, 1, 0], [-1, 1, 0]], float)
    >>> far, _ = unexplained_points(pts, xyz, np.array([[0, 1, 2], [0, 2, 3]]), gap_m=0.05, cluster_m=0.1, min_points=3)
    >>> far.tolist()
    [False, False, True, True, True]
    """
    from tasks.repair.mesh import ClosestPoint

    if not len(pts):
        return np.zeros(0, bool), np.zeros(0, np.int64)
    if len(faces):
        fid, _, d = ClosestPoint(xyz, faces).query(pts)
        far = d > gap_m
    else:
        fid, far = np.full(len(pts), -1, np.int64), np.ones(len(pts), bool)
    idx = np.flatnonzero(far)
    if len(idx) and min_points > 1:
        n = cKDTree(pts[idx]).query_ball_point(pts[idx], r=cluster_m, return_length=True)
        far[idx[n < min_points]] = False
    return far, fid


def agreeing_faces(xyz: np.ndarray, zone_faces: np.ndarray, context_faces: np.ndarray, pts: np.ndarray, *,
                   gap_m: float, band_m: float, cluster_m: float = 0.15, min_points: int = 3,
                   min_area_m2: float = 1.0, stats: dict | None = None) -> np.ndarray:
    """(mz,) bool: zone faces (mz, 3) int64 into xyz (n, 3) to keep as they are: not the closest face of an
    unexplained MLS point (:func:`unexplained_points` against zone + context faces (mc, 3)), and none of
    their corners, centroid or samples (every ``band_m`` / 2) within ``band_m`` of such a point or face.
    pts (p, 3): the region's MLS points.
    ``stats`` (optional) gets the counts.

    >>> g = np.stack(np.meshgrid(np.arange(0, 4, 0.05), np.arange(0, 1, 0.05)), -1).reshape(-1, 2)
    >>> pts = np.c_[g, np.zeros(len(g))]
    >>> xyz = np.array([[x, y, 0.0] for x in range(5) for y in (0, 1)])
    >>> xyz[8:, 2] = 0.3                                           # the strip x in [3, 4] bulges out
    >>> f = np.array([[2 * i, 2 * i + 2, 2 * i + 3] for i in range(4)] + [[2 * i, 2 * i + 3, 2 * i + 1] for i in range(4)])
    >>> keep = agreeing_faces(xyz, f, np.zeros((0, 3), np.int64), pts, gap_m=0.05, band_m=0.5, min_area_m2=0.5)
    >>> keep.reshape(2, 4).all(axis=0).tolist()                    # [0, 1] and [1, 2] kept; [2, 3] rebuilt with [3, 4]
    [True, True, False, False]
    """
    zone_faces = np.asarray(zone_faces, np.int64)
    mz = len(zone_faces)
    if not (mz and len(pts)):
        return np.zeros(mz, bool)
    faces = np.concatenate([zone_faces, np.asarray(context_faces, np.int64).reshape(-1, 3)])
    bad, fid = unexplained_points(pts, xyz, faces, gap_m=gap_m, cluster_m=cluster_m, min_points=min_points)
    keep = np.ones(mz, bool)
    if bad.any():
        step = max(band_m / 2, 0.05)
        s, sf = sample_surface(xyz, zone_faces, spacing_m=step, rng=0)
        q = np.concatenate([xyz[zone_faces].reshape(-1, 3), xyz[zone_faces].mean(axis=1), s])
        qf = np.r_[np.repeat(np.arange(mz), 3), np.arange(mz), sf]
        owner = np.zeros(mz, bool)  # the zone faces closest to an unexplained point: the surface that is wrong
        owner[fid[bad & (fid >= 0) & (fid < mz)]] = True  # (a recess 1 m deep: its faces are 1 m from the scan)
        seeds = np.concatenate([pts[bad], q[owner[qf]]])
        near = np.isfinite(cKDTree(seeds).query(q, distance_upper_bound=band_m)[0])
        keep[qf[near]] = False
        keep[owner] = False
    if min_area_m2 > 0 and keep.any() and not keep.all():
        from tasks.repair.chart import face_components

        idx = np.flatnonzero(keep)
        comp = face_components(zone_faces[idx], len(xyz))
        area = face_areas(xyz, zone_faces[idx], np.float64)
        keep[idx[np.bincount(comp, weights=area)[comp] < min_area_m2]] = False
    if stats is not None:
        stats["agreeing"] = {"unexplained_points": int(bad.sum()), "kept_faces": int(keep.sum())}
    return keep


__all__ = ["agreeing_faces", "unexplained_points"]
