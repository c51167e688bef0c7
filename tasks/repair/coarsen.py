"""Fewer points where the rebuilt surface is flat: the triangulation's input, coarsened with an error bound.

The fusion keeps one MLS point per ``fusion.mls_spacing_m`` voxel, which is what a window reveal or an
eave needs, but a flat wall then carries ~8 rebuilt faces per input face at real MLS density. Here a
point may go only where its neighbourhood of radius ``coarse_m`` is a plane within ``tolerance_m``
(RMS distance of the neighbours to their own PCA plane) and the point lies inside that neighbourhood
(not at the scan's edge, where dropping it would shrink the rebuilt surface). Those points are thinned
to one per ``coarse_m`` voxel; every other point stays. A Delaunay triangulation of what is left departs
from the dropped points by about the tolerance, as they lay within it of the plane their kept
neighbours span.

Frames and units: campus-local metres (float64).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.repair.fuse import thin_points

__all__ = ["flat_points", "coarsen_flat"]

CHUNK = 16384  # points per k-NN query (~50 MB of neighbour arrays)
CENTROID_SHIFT = 0.2  # in-plane shift of the neighbours' centroid, x coarse_m, above which a point is at an edge


def flat_points(xyz: np.ndarray, coarse_m: float, tolerance_m: float, max_neighbours: int = 32) -> np.ndarray:
    """(n,) bool: points whose neighbours within ``coarse_m`` fit a plane to ``tolerance_m`` RMS and sit
    around them (the neighbours' centroid within ``CENTROID_SHIFT`` x ``coarse_m`` of the point, in the
    plane). xyz: (n, 3) float metres, about evenly spaced (thinned); at most ``max_neighbours`` nearest are
    asked, so a point with more within the radius is judged on its nearest ones. Fewer than 6 neighbours:
    not flat.

    >>> g = np.stack(np.meshgrid(np.arange(20), np.arange(20), [0.0]), -1).reshape(-1, 3) * 0.05
    >>> f = flat_points(g, 0.15, 0.01)
    >>> bool(f[10 * 20 + 10]), bool(f[0])          # the middle of a plane, its corner
    (True, False)
    >>> g[:, 2] = np.where(g[:, 0] > 0.5, 0.1, 0.0)   # a 10 cm step across it
    >>> bool(flat_points(g, 0.15, 0.01)[10 * 20 + 10])
    False
    """
    xyz = np.asarray(xyz, np.float64)
    n = len(xyz)
    out = np.zeros(n, bool)
    if n < 6:
        return out
    tree, k = cKDTree(xyz), min(max_neighbours, n)
    local = (xyz - xyz.mean(axis=0)).astype(np.float32)  # a region spans < 1 km: ~0.1 mm steps at worst
    for s in range(0, n, CHUNK):  # bounded working set
        d, j = tree.query(xyz[s:s + CHUNK], k=k, distance_upper_bound=coarse_m)
        ok = np.isfinite(d)
        cnt = np.maximum(ok.sum(axis=1), 1).astype(np.float32)
        w = ok[:, :, None].astype(np.float32)
        nb = local[np.where(ok, j, 0)] - local[s:s + CHUNK, None, :]  # relative to the point
        mean = (nb * w).sum(axis=1) / cnt[:, None]
        nb = (nb - mean[:, None, :]) * w
        lam, vec = np.linalg.eigh(np.einsum("nki,nkj->nij", nb, nb) / cnt[:, None, None])
        normal = vec[:, :, 0]
        planar = np.sqrt(np.maximum(lam[:, 0], 0.0)) <= tolerance_m
        shift = mean - np.einsum("ij,ij->i", mean, normal)[:, None] * normal
        inside = np.linalg.norm(shift, axis=1) <= CENTROID_SHIFT * coarse_m
        out[s:s + CHUNK] = (ok.sum(axis=1) >= 6) & planar & inside
    return out


def coarsen_flat(xyz: np.ndarray, coarse_m: float, tolerance_m: float) -> np.ndarray:
    """Sorted indices of the points to keep: every point that is not flat (:func:`flat_points`), and one
    flat point per ``coarse_m`` voxel (the one nearest its flat points' centroid). xyz: (n, 3).

    >>> g = np.stack(np.meshgrid(np.arange(40), np.arange(40), [0.0]), -1).reshape(-1, 3) * 0.05
    >>> keep = coarsen_flat(g, 0.15, 0.01)
    >>> 0.1 < len(keep) / len(g) < 0.5, bool(np.isin(0, keep))   # fewer points; the corner stays
    (True, True)
    """
    xyz = np.asarray(xyz, np.float64)
    if coarse_m <= 0 or len(xyz) < 6:
        return np.arange(len(xyz))
    flat = np.flatnonzero(flat_points(xyz, coarse_m, tolerance_m))
    keep = np.ones(len(xyz), bool)
    keep[flat] = False
    keep[flat[thin_points(xyz[flat], coarse_m)]] = True
    return np.flatnonzero(keep)
