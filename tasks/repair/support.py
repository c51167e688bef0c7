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
    from tasks.repair.mesh import ClosestPoint

    if not len(faces):
        return 0.0
    pts, _ = sample_surface(xyz, faces, spacing_m=step_m, rng=0)
    if not len(pts):
        return 0.0
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
    return float((~ok).mean())


__all__ = ["unsupported_share"]
