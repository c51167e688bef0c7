"""Building footprints from a mesh on a ground grid: which ground cells a building stands on, its area, height
and centroid, and which building a point (a facade's scan) belongs to. Pure (numpy, scipy).

A mesh carries no building ids, so they are found from its heights (campus-local metres, z up):

1. **cell heights** (:func:`cell_heights`): every face's centroid and corners land in a ``cell_m`` ground cell
   (corners too, so a thin wall is not lost); a face wider than a cell (a roof of two triangles, a CAD wall) is
   also sampled on a barycentric grid at most half a cell apart, so it covers every cell under it. Per cell: the
   max and the min z. Cells are anchored at (0, 0) (``floor(xy / cell_m)``), so tiles are measured one by one
   and their cells merged (:meth:`CellHeights.merge`), never a whole city's triangles at once;
2. **ground** per cell: the min-z raster, empty cells filled from the nearest filled one, under a minimum filter
   over a ``ground_window_m`` square (a roof cell finds the street beside its building);
3. **building cells**: max z above the ground by more than ``min_height_m``; cells enclosed by building cells
   (the middle of a roof wider than the window, which the filter could not see past) count too where their min
   z is that high above the ground around the building, so a courtyard at street level does not;
4. **buildings**: 8-connected components of building cells, their area the cells' with those on the border
   (a 4-neighbour outside) counted half, since the facade runs through them (a 10 x 8 m box covers 11 x 9
   cells, 99 m²; its estimate is 81 m²); components under ``min_area_m2`` are dropped. Ids 1, 2, … in the
   order of their centroids (y, then x): the same mesh gives the same ids, in any face order.

Memory: about 30 bytes per cell of the campus's bounding box (a 2 x 2 km campus at 1 m: 120 MB).

    >>> import numpy as np
    >>> iy, ix = np.mgrid[0:30, 0:30]  # 30 x 30 cells: a 6 x 5 cell block 8 m high, flat ground around it
    >>> block = (ix >= 10) & (ix < 16) & (iy >= 10) & (iy < 15)
    >>> cells = CellHeights(1.0, np.stack([ix.ravel(), iy.ravel()], 1), np.where(block, 8.0, 0.0).ravel(),
    ...                     np.zeros(900))
    >>> fp = footprints_of(cells)
    >>> fp
    Footprints(1 buildings, 30 x 30 cells of 1 m)
    >>> fp.to_json()["buildings"]
    [{'id': 1, 'area_m2': 21.0, 'height_m': 8.0, 'centroid': [13.0, 12.5]}]
    >>> fp.building_of(np.array([[12.5, 12.5], [17.2, 12.0], [25.0, 25.0]]))  # inside, 1.2 m out, far
    array([1, 1, 0], dtype=int32)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

_FOUR = ndimage.generate_binary_structure(2, 1)
_EIGHT = np.ones((3, 3), bool)
_CHUNK_FACES = 200_000  # faces sampled at a time (memory: about 1 kB each at most, for a face of 2.3 m)
_SNAP = 1e-6  # cells: a sample a round-off below a cell's edge (a wall on it) goes to that cell, in any corner order


@dataclass(frozen=True, eq=False)
class CellHeights:
    """Max and min z per ground cell: ij (k, 2) int64 cell indices ``floor(xy / cell_m)`` (unique, sorted by
    (i, j)), zmax and zmin (k,) float64 metres. Mergeable: the cells of tiles merge into the campus's."""

    cell_m: float
    ij: np.ndarray
    zmax: np.ndarray
    zmin: np.ndarray

    @classmethod
    def merge(cls, parts: list[CellHeights], cell_m: float = 1.0) -> CellHeights:
        """One CellHeights of ``parts`` (all of one ``cell_m``): a cell's max of the max z, min of the min z."""
        ij = np.concatenate([p.ij for p in parts] + [np.zeros((0, 2), np.int64)])
        zmax = np.concatenate([p.zmax for p in parts] + [np.zeros(0)])
        zmin = np.concatenate([p.zmin for p in parts] + [np.zeros(0)])
        return _reduced(parts[0].cell_m if parts else cell_m, ij, zmax, zmin)


def _reduced(cell_m: float, ij: np.ndarray, zmax: np.ndarray, zmin: np.ndarray) -> CellHeights:
    """CellHeights of rows that may repeat a cell: one sort over packed keys, reduced per cell."""
    if not len(ij):
        return CellHeights(float(cell_m), np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0))
    ij = np.asarray(ij, np.int64)
    key = ((ij[:, 0] + (1 << 30)) << 31) | (ij[:, 1] + (1 << 30))  # cell indices |i| < 2**30
    order = np.argsort(key, kind="stable")
    ks = key[order]
    starts = np.flatnonzero(np.r_[True, ks[1:] != ks[:-1]])
    return CellHeights(float(cell_m), ij[order[starts]], np.maximum.reduceat(np.asarray(zmax, np.float64)[order], starts),
                       np.minimum.reduceat(np.asarray(zmin, np.float64)[order], starts))


def _face_points(tri: np.ndarray, cell_m: float) -> np.ndarray:
    """(p, 3) float64 points of the (m, 3, 3) triangles: corners and centroid of each; faces wider (in xy) than a
    cell also a barycentric grid at most half a cell apart."""
    pts = [tri.reshape(-1, 3), tri.mean(axis=1)]
    edge = np.linalg.norm(tri[:, [1, 2, 0], :2] - tri[:, :, :2], axis=2).max(axis=1)
    n = np.where(edge > cell_m, np.ceil(edge / (0.5 * cell_m)), 1).astype(np.int64)
    for k in np.unique(n[n > 1]):  # one pass per subdivision count, not per face
        i, j = np.nonzero(np.add.outer(np.arange(k + 1), np.arange(k + 1)) <= k)
        w = np.stack([i, j, k - i - j], 1) / k  # (q, 3) barycentric weights
        pts.append(np.einsum("qc,mcd->mqd", w, tri[n == k]).reshape(-1, 3))
    return np.concatenate(pts)


def cell_heights(triangles: np.ndarray, cell_m: float = 1.0) -> CellHeights:
    """Max and min z per ``cell_m`` ground cell of (m, 3, 3) float triangles (campus-local metres, z up)."""
    tri = np.asarray(triangles, np.float64).reshape(-1, 3, 3)
    parts = []
    for a in range(0, len(tri), _CHUNK_FACES):
        p = _face_points(tri[a:a + _CHUNK_FACES], cell_m)
        parts.append(_reduced(cell_m, np.floor(p[:, :2] / cell_m + _SNAP).astype(np.int64), p[:, 2], p[:, 2]))
    return CellHeights.merge(parts, cell_m)


@dataclass(frozen=True, eq=False)
class Footprints:
    """Buildings on a ground grid. The cell (row iy, column ix) of ``labels`` covers
    ``[x0 + ix * cell_m, x0 + (ix + 1) * cell_m) x [y0 + iy * cell_m, …)`` (campus-local metres);
    labels: (ny, nx) int32 building id per cell (0: none). Per building i (id i + 1): area_m2 (n,) float64,
    height_m (n,) float64 (its highest cell's max z above the ground), centroid_xy (n, 2) float64 metres."""

    x0: float
    y0: float
    cell_m: float
    labels: np.ndarray
    area_m2: np.ndarray
    height_m: np.ndarray
    centroid_xy: np.ndarray

    @property
    def n(self) -> int:
        return len(self.area_m2)

    @property
    def ids(self) -> np.ndarray:
        """(n,) int32 building ids, 1-based."""
        return np.arange(1, self.n + 1, dtype=np.int32)

    def __repr__(self) -> str:
        ny, nx = self.labels.shape
        return f"Footprints({self.n} buildings, {ny} x {nx} cells of {self.cell_m:g} m)"

    def building_of(self, xy: np.ndarray, pad_m: float = 1.5) -> np.ndarray:
        """(k,) int32 building id of each of the (k, 2) float points (campus-local metres; 0: no building).
        A point within ``pad_m`` (``round(pad_m / cell_m)`` cells) of a building's cell counts as that building,
        the nearest one where two are near: a facade's scan lies on its footprint's border or just outside it.
        Only the labels around the points are dilated (memory: the points' bounding box)."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        out = np.zeros(len(xy), np.int32)
        if not len(xy) or not self.n:
            return out
        r = int(np.floor(pad_m / self.cell_m + 0.5))
        shape = np.array(self.labels.shape[::-1])  # (nx, ny)
        c = np.floor((xy - (self.x0, self.y0)) / self.cell_m).astype(np.int64)
        near = np.all((c >= -r) & (c < shape + r), axis=1)  # farther out: no building within pad_m
        if not near.any():
            return out
        c = c[near]
        lo, hi = np.maximum(c.min(0) - r, -r), np.minimum(c.max(0) + r + 1, shape + r)
        a, b = np.maximum(lo, 0), np.minimum(hi, shape)
        crop = np.zeros((hi[1] - lo[1], hi[0] - lo[0]), np.int32)
        if np.all(a < b):
            crop[a[1] - lo[1]:b[1] - lo[1], a[0] - lo[0]:b[0] - lo[0]] = self.labels[a[1]:b[1], a[0]:b[0]]
        if r > 0 and crop.any():
            dist, (iy, ix) = ndimage.distance_transform_edt(crop == 0, return_indices=True)
            crop = np.where(dist <= r, crop[iy, ix], 0)
        out[near] = crop[c[:, 1] - lo[1], c[:, 0] - lo[0]]
        return out

    def to_json(self) -> dict:
        """The grid and the buildings, without the raster: {"cell_m", "origin_xy", "shape", "buildings": [{"id",
        "area_m2", "height_m", "centroid": [x, y]}]} (campus-local metres)."""
        return {"cell_m": self.cell_m, "origin_xy": [self.x0, self.y0], "shape": list(self.labels.shape),
                "buildings": [{"id": int(i), "area_m2": round(float(a), 1), "height_m": round(float(h), 2),
                               "centroid": [round(float(x), 2), round(float(y), 2)]}
                              for i, a, h, (x, y) in zip(self.ids, self.area_m2, self.height_m, self.centroid_xy)]}


def _ground(zmin: np.ndarray, filled: np.ndarray, window_cells: int) -> np.ndarray:
    """(ny, nx) ground height: ``zmin`` with empty cells taken from the nearest filled one, minimum-filtered."""
    if not filled.all():
        idx = ndimage.distance_transform_edt(~filled, return_distances=False, return_indices=True)
        zmin = zmin[tuple(idx)]
    return ndimage.minimum_filter(zmin, size=window_cells, mode="nearest")


def _raised_holes(tall: np.ndarray, filled: np.ndarray, zmin: np.ndarray, ground: np.ndarray,
                  min_height_m: float) -> np.ndarray:
    """(ny, nx) bool: cells enclosed by ``tall`` cells whose min z is ``min_height_m`` above the ground of the
    nearest cell outside (a roof's middle, not a courtyard)."""
    holes = ndimage.binary_fill_holes(tall) & ~tall & filled
    if not holes.any():
        return holes
    idx = ndimage.distance_transform_edt(tall | holes, return_distances=False, return_indices=True)
    return holes & (zmin - ground[tuple(idx)] > min_height_m)


def footprints_of(cells: CellHeights, min_height_m: float = 2.5, min_area_m2: float = 20.0,
                  ground_window_m: float = 25.0) -> Footprints:
    """The buildings of ``cells`` (see the module docstring): cells more than ``min_height_m`` above the ground
    (a minimum filter over ``ground_window_m``), 8-connected, at least ``min_area_m2`` each."""
    cell = cells.cell_m
    if not len(cells.ij):
        z = np.zeros(0)
        return Footprints(0.0, 0.0, cell, np.zeros((0, 0), np.int32), z, z, np.zeros((0, 2)))
    i0, j0 = cells.ij.min(0)
    nx, ny = cells.ij.max(0) - (i0, j0) + 1
    ix, iy = cells.ij[:, 0] - i0, cells.ij[:, 1] - j0
    filled = np.zeros((ny, nx), bool)
    zmax, zmin = np.zeros((ny, nx), np.float32), np.zeros((ny, nx), np.float32)
    filled[iy, ix], zmax[iy, ix], zmin[iy, ix] = True, cells.zmax, cells.zmin
    ground = _ground(zmin, filled, max(1, round(ground_window_m / cell)) | 1)
    tall = filled & (zmax - ground > min_height_m)
    tall |= _raised_holes(tall, filled, zmin, ground, min_height_m)
    labels, n = ndimage.label(tall, structure=_EIGHT)
    border = tall & ~ndimage.binary_erosion(tall, structure=_FOUR, border_value=0)
    count = np.bincount(labels.ravel(), minlength=n + 1)[1:]
    area = (count - 0.5 * np.bincount(labels[border], minlength=n + 1)[1:]) * cell * cell
    yy, xx = np.nonzero(labels)
    lab = labels[yy, xx]
    cx = np.bincount(lab, weights=(xx + i0 + 0.5) * cell, minlength=n + 1)[1:] / np.maximum(count, 1)
    cy = np.bincount(lab, weights=(yy + j0 + 0.5) * cell, minlength=n + 1)[1:] / np.maximum(count, 1)
    height = np.asarray(ndimage.maximum(zmax - ground, labels, np.arange(1, n + 1)), np.float64).reshape(n)
    keep = np.flatnonzero(area >= min_area_m2)
    keep = keep[np.lexsort((cx[keep], cy[keep]))]  # ids by centroid: y, then x
    remap = np.zeros(n + 1, np.int32)
    remap[keep + 1] = np.arange(1, len(keep) + 1, dtype=np.int32)
    return Footprints(float(i0 * cell), float(j0 * cell), cell, remap[labels], area[keep], height[keep],
                      np.stack([cx[keep], cy[keep]], 1))


def footprints(triangles: np.ndarray, cell_m: float = 1.0, min_height_m: float = 2.5, min_area_m2: float = 20.0,
               ground_window_m: float = 25.0) -> Footprints:
    """The buildings of a mesh's (m, 3, 3) float triangles (campus-local metres, z up): :func:`footprints_of` its
    :func:`cell_heights`."""
    return footprints_of(cell_heights(triangles, cell_m), min_height_m, min_area_m2, ground_window_m)


__all__ = ["CellHeights", "Footprints", "cell_heights", "footprints", "footprints_of"]
