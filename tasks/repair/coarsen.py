"""Fewer points where the rebuilt surface is flat: the triangulation's input, coarsened with an error bound.

The fusion keeps one MLS point per ``fusion.mls_spacing_m`` voxel, which is what a window reveal or an
eave needs, but a flat wall then carries ~8 rebuilt faces per input face at real MLS density. Here a
point may go only where its neighbourhood of radius ``coarse_m`` is a plane within ``tolerance_m``
(RMS distance of the neighbours to their own PCA plane) and the neighbours surround the point (not at
the scan's edge, where dropping it would shrink the rebuilt surface, nor on the near side of a step).
Those points are thinned to one per ``coarse_m`` voxel; every other point stays. A Delaunay
triangulation of what is left departs from the dropped points by about the tolerance, as they lay
within it of the plane their kept neighbours span.

Frames and units: campus-local metres (float64).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ms3d_model.kernels import local_planes
from tasks.repair.fuse import thin_points

__all__ = ["coarsen_flat", "flat_points", "one_per_voxel", "thin_with_detail"]

CHUNK = 16384  # points per k-NN query (~50 MB of neighbour arrays)
MAX_GAP = np.radians(120)  # an empty sector of the neighbourhood wider than this: the point is at an edge


def one_per_voxel(xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """Sorted indices of the first point (in row order) of every voxel of side ``voxel_m``, the grid
    anchored at the points' minimum. Unlike :func:`tasks.repair.fuse.thin_points` (the point nearest the
    voxel's centroid) this does not favour points near the surface's middle, so a neighbourhood of them
    keeps the surface's roughness. xyz: (n, 3).

    >>> one_per_voxel(np.array([[0.0, 0, 0], [0.04, 0, 0], [0.5, 0, 0]]), 0.1).tolist()
    [0, 2]
    """
    if not len(xyz):
        return np.zeros(0, np.int64)
    packed = _packed_cells(np.floor((xyz - xyz.min(axis=0)) / voxel_m).astype(np.int64))
    return np.sort(np.unique(packed, return_index=True)[1])


def flat_points(xyz: np.ndarray, coarse_m: float, tolerance_m: float, max_neighbours: int = 32,
                edges: bool = True) -> np.ndarray:
    """(n,) bool: points whose neighbours within ``coarse_m`` fit a plane to ``tolerance_m`` RMS and sit
    all around them (no empty sector wider than ``MAX_GAP`` in their plane: not at an edge; ``edges`` false:
    the plane alone decides).

    xyz: (n, 3) float metres. The neighbours are taken from the points thinned to one per ``coarse_m / 2``
    voxel, so that the nearest ``max_neighbours`` span the whole radius at any density (a 5 cm-thinned
    real-density scan holds 2-3 points per voxel across a wall's noise: its 32 nearest points spanned only
    ~11 cm and missed steps that a triangle of the coarse surface then crossed). Fewer than 6 neighbours:
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
    ref = one_per_voxel(xyz, coarse_m / 2)  # the same ~20 neighbours whatever the density: the whole radius
    tree, k = cKDTree(xyz[ref]), min(max_neighbours, len(ref))
    local = xyz - xyz.mean(axis=0)  # a region spans < 1 km
    local_ref = np.ascontiguousarray(local[ref])
    for s in range(0, n, CHUNK):  # bounded working set
        d, j = tree.query(xyz[s:s + CHUNK], k=k, distance_upper_bound=coarse_m)
        j = np.asarray(j, np.int64).reshape(len(d), k)
        out[s:s + CHUNK] = local_planes(local[s:s + CHUNK], local_ref, j, np.asarray(d).reshape(len(j), k),
                                        tolerance_m, edges, MAX_GAP)
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


def thin_with_detail(xyz: np.ndarray, spacing_m: float, detail_m: float, radius_m: float, tolerance_m: float
                     ) -> np.ndarray:
    """Sorted indices of the points to fuse: one per ``spacing_m`` voxel where the surface is flat, one per
    ``detail_m`` voxel where it is not. xyz: (n, 3) float metres (campus-local).

    The points are first thinned to one per ``spacing_m`` voxel (:func:`tasks.repair.fuse.thin_points`);
    those whose neighbours within ``radius_m`` do not fit a plane to ``tolerance_m`` RMS (:func:`flat_points`
    without its edge test: a frame, a reveal, a balcony's edge) mark their voxel, and inside a marked voxel
    the points are thinned to one per ``detail_m`` voxel instead. The ``detail_m`` grid nests in the ``spacing_m`` one when
    ``spacing_m / detail_m`` is an integer; otherwise a fine voxel belongs to the coarse voxel of its point.
    ``detail_m`` <= 0 or >= ``spacing_m``: the plain ``spacing_m`` thinning.

    >>> g = np.stack(np.meshgrid(np.arange(80), np.arange(80), [0.0]), -1).reshape(-1, 3) * 0.01
    >>> len(thin_with_detail(g, 0.05, 0.025, 0.15, 0.015)) < 0.3 * len(g)   # the plane's middle stays coarse
    True
    >>> g[:, 2] = np.where(g[:, 0] > 0.4, 0.1, 0.0)                          # a 10 cm step across it
    >>> flat = thin_with_detail(g, 0.05, 0.0, 0.15, 0.015)
    >>> len(thin_with_detail(g, 0.05, 0.025, 0.15, 0.015)) > len(flat)       # finer along the step
    True
    """
    xyz = np.asarray(xyz, np.float64)
    coarse = thin_points(xyz, spacing_m)
    if detail_m <= 0 or detail_m >= spacing_m or len(coarse) < 6:
        return coarse
    rough = ~flat_points(xyz[coarse], radius_m, tolerance_m, edges=False)  # the scan's edge needs no detail
    if not rough.any():
        return coarse
    cell = _packed_cells(np.floor(xyz / spacing_m).astype(np.int64))
    marked = np.isin(cell, cell[coarse[rough]])
    fine = np.flatnonzero(marked)
    fine = fine[thin_points(xyz[fine], detail_m)]
    return np.sort(np.concatenate([coarse[~marked[coarse]], fine]))


def _packed_cells(cells: np.ndarray) -> np.ndarray:
    """(n,) int64 key of each (n, 3) int64 voxel index, equal exactly when the rows are equal."""
    c = cells - cells.min(axis=0)
    span = c.max(axis=0) + 1
    return (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]
