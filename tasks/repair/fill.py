"""Keep the input surface where the MLS says nothing (repair never makes an unseen surface worse).

A region's charts are triangulated from its fused points: the mesh vertices the fusion kept and the
MLS points it accepted. Where the zone has neither (an upper wall the street scanner never reached, the
inside of a city model's big triangle whose corners the fusion replaced), a Delaunay of the disc
would span the gap with long chords between far boundary vertices, cutting through the building.
:func:`unseen_samples` samples the zone's own surface there, so the rebuilt surface follows the input
mesh wherever no evidence contradicts it, and the chords never form.

A zone sample is *unseen* when no fused point's foot (its closest point on the zone surface) lies within
``step_m`` of it, and no vertex the fusion replaced lies within ``step_m`` (a replaced vertex is one the
MLS contradicts: a protrusion cut back is not put back).

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.geometry.sampling import sample_surface

SOURCE_FILL = 3  # RebuiltMesh.source of a sample of the input surface


def surface_feet(xyz: np.ndarray, faces: np.ndarray, pts: np.ndarray, reach_m: float) -> np.ndarray:
    """Closest points on the surface (xyz (n, 3), faces (m, 3)) of the points (k, 3) within reach_m: (j, 3)."""
    from tasks.repair.mesh import ClosestPoint

    if not (len(faces) and len(pts)):
        return np.zeros((0, 3))
    fid, bary, dist = ClosestPoint(xyz, faces).query(pts)
    ok = (fid >= 0) & (dist <= reach_m)
    return np.einsum("kc,kcd->kd", bary[ok], np.asarray(xyz, np.float64)[faces[fid[ok]]])


def unseen_samples(xyz: np.ndarray, zone_faces: np.ndarray, fused_xyz: np.ndarray, replaced_xyz: np.ndarray,
                   *, step_m: float, reach_m: float) -> np.ndarray:
    """Samples (s, 3) float64 of the zone surface that no fused point nor replaced vertex stands near.

    xyz: (n, 3) region vertex positions; zone_faces: (m, 3) int64 faces being replaced; fused_xyz: (k, 3)
    fused points; replaced_xyz: (r, 3) positions of the zone vertices the fusion replaced; step_m:
    sample spacing and the clearance radius; reach_m: fused points farther than this from the zone say
    nothing of it. step_m <= 0 returns no samples.

    >>> sq = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
    >>> f = np.array([[0, 1, 2], [0, 2, 3]])
    >>> seen = np.array([[x, y, 0.0] for x in np.arange(0, 2, 0.1) for y in np.arange(0, 4, 0.1)])
    >>> s = unseen_samples(sq, f, seen, np.zeros((0, 3)), step_m=0.5, reach_m=1.0)
    >>> bool(len(s) > 20 and s[:, 0].min() > 1.9)
    True
    """
    if step_m <= 0 or not len(zone_faces):
        return np.zeros((0, 3))
    samples, _ = sample_surface(xyz, zone_faces, spacing_m=step_m, rng=0)
    if not len(samples):
        return samples
    free = np.ones(len(samples), bool)
    feet = surface_feet(xyz, zone_faces, fused_xyz, reach_m)
    if len(feet):
        free &= ~np.isfinite(cKDTree(feet).query(samples, distance_upper_bound=step_m)[0])
    if len(replaced_xyz):
        free &= ~np.isfinite(cKDTree(replaced_xyz).query(samples, distance_upper_bound=step_m)[0])
    return samples[free]


__all__ = ["SOURCE_FILL", "surface_feet", "unseen_samples"]
