"""Is a rebuilt surface supported by the evidence? (repair never makes a region worse)

A rebuilt region replaces the input only where its surface rests on something: the MLS points (the
scanner saw a surface there) or the input mesh itself (kept where the MLS saw nothing:
:mod:`tasks.repair.fill`). A rebuilt face that lies on neither (a chord across missing data, a fold)
is invented geometry. :func:`unsupported_share` samples the rebuilt surface and measures the area
share of such samples; the repair falls back to the input mesh when it is too large
(``mesh.max_unsupported_share``).

A sample is supported by the MLS when an MLS point lies within ``reach_m`` of it and the sample is
within ``offset_m`` of that point's tangent plane; by the input when it lies within ``offset_m`` of
the input surface (the zone's faces).

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.geometry.sampling import sample_surface


def _sample_support(xyz: np.ndarray, faces: np.ndarray, mls: np.ndarray, mls_n: np.ndarray, zone_xyz: np.ndarray,
                    zone_faces: np.ndarray, *, reach_m: float, offset_m: float, step_m: float,
                    tree: cKDTree | None) -> tuple[np.ndarray, np.ndarray]:
    """Samples of the surface (xyz, faces) every ``step_m`` plus each face's centroid: ((k,) bool supported,
    (k,) int64 their face)."""
    from tasks.repair.mesh import ClosestPoint

    s, sf = sample_surface(xyz, faces, spacing_m=step_m, rng=0)
    pts = np.concatenate([xyz[faces].mean(axis=1), s])
    pf = np.r_[np.arange(len(faces)), sf]
    ok = np.zeros(len(pts), bool)
    if len(mls):
        d, j = (tree if tree is not None else cKDTree(mls)).query(pts, distance_upper_bound=reach_m)
        hit = np.isfinite(d)
        jj = np.where(hit, j, 0)
        off = np.abs(np.einsum("ij,ij->i", pts - mls[jj], mls_n[jj]))
        ok |= hit & (off <= offset_m)
    if len(zone_faces) and not ok.all():
        _, _, dz = ClosestPoint(zone_xyz, zone_faces).query(pts[~ok])
        ok[np.flatnonzero(~ok)[dz <= offset_m]] = True
    return ok, pf


def unsupported_faces(xyz: np.ndarray, faces: np.ndarray, mls: np.ndarray, mls_n: np.ndarray, zone_xyz: np.ndarray,
                      zone_faces: np.ndarray, *, reach_m: float = 0.3, offset_m: float = 0.05, step_m: float = 0.1,
                      tree: cKDTree | None = None) -> np.ndarray:
    """(m,) bool: rebuilt faces (m, 3) into xyz (n, 3) with most of their samples (centroid and one every
    ``step_m``) supported neither by an MLS point (within ``reach_m``, the sample within ``offset_m`` of its
    tangent plane) nor by the input zone surface (within ``offset_m``): chords of the chart triangulation
    across a scan gap, a corner or a recess, which lie off every surface the evidence shows.

    >>> sq = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]], float)
    >>> f = np.array([[0, 1, 2], [0, 2, 3]])
    >>> g = np.stack(np.meshgrid(np.arange(0, 2, 0.05), np.arange(0, 2, 0.05)), -1).reshape(-1, 2)
    >>> mls = np.c_[g, np.zeros(len(g))]
    >>> mls = mls[mls[:, 0] > mls[:, 1] + 0.3]                    # the scan saw the lower-right half only
    >>> up = np.tile([0.0, 0.0, 1.0], (len(mls), 1))
    >>> no_zone = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    >>> unsupported_faces(sq, f, mls, up, *no_zone).tolist()
    [False, True]
    """
    if not len(faces):
        return np.zeros(0, bool)
    ok, pf = _sample_support(xyz, faces, mls, mls_n, zone_xyz, zone_faces, reach_m=reach_m, offset_m=offset_m,
                             step_m=step_m, tree=tree)
    bad = np.bincount(pf, weights=~ok, minlength=len(faces))
    return bad > 0.5 * np.bincount(pf, minlength=len(faces))


def unsupported_share(xyz: np.ndarray, faces: np.ndarray, mls: np.ndarray, mls_n: np.ndarray,
                      zone_xyz: np.ndarray, zone_faces: np.ndarray, *, reach_m: float = 0.6,
                      offset_m: float = 0.1, step_m: float = 0.2, tree: cKDTree | None = None) -> float:
    """Area share in [0, 1] of the rebuilt surface (xyz (n, 3), faces (m, 3)) that neither the MLS
    points (p, 3) with unit normals (p, 3) nor the input zone surface (zone_xyz, zone_faces) support.
    0 for an empty surface. tree: the k-d tree of ``mls`` when the caller has it.

    >>> sq = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0]], float)
    >>> f = np.array([[0, 1, 2], [0, 2, 3]])
    >>> g = np.stack(np.meshgrid(np.arange(0, 1, 0.1), np.arange(0, 2, 0.1)), -1).reshape(-1, 2)
    >>> mls = np.c_[g, np.zeros(len(g))]
    >>> up = np.tile([0.0, 0.0, 1.0], (len(mls), 1))
    >>> no_zone = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    >>> round(unsupported_share(sq, f, mls, up, *no_zone, reach_m=0.3), 1)    # the half x > 1.3 is bare
    0.4
    >>> unsupported_share(sq, f, mls, up, sq, f)                              # the input holds it all
    0.0
    """
    if not len(faces):
        return 0.0
    ok, _ = _sample_support(xyz, faces, mls, mls_n, zone_xyz, zone_faces, reach_m=reach_m, offset_m=offset_m,
                             step_m=step_m, tree=tree)
    ok = ok[len(faces):]  # the area samples only (the centroids would weigh each face once more)
    return float((~ok).mean()) if len(ok) else 0.0


__all__ = ["unsupported_faces", "unsupported_share"]
