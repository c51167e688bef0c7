"""The global patch grid and ground tiles: the one place that owns the key arithmetic.

The grid is anchored in projected **world** coordinates, not at the campus origin: patch
``(i, j, k) = floor((x_world - anchor) / size)``. A place therefore keeps its patch id in every run
and every campus extent (adding mesh tiles to the west moves the campus origin, never an id), and a
label CSV of ``i,j,k`` stays right. The campus origin is only the float64 offset that keeps stored
coordinates float32; cells are always computed in float64 as ``origin + local``, so every stage that
starts from the same stored float32 values gets the same cells.

A ground tile ``(ix, iy)`` covers ``[ix*t, (ix+1)*t) x [iy*t, (iy+1)*t)`` in world metres (minus the
anchor); a patch belongs to the tile holding its centre, so no patch is split between tiles.

Patch keys pack ``(i, j, k)`` into one int64: biased fields of 22, 25 and 16 bits, ``i`` highest, so
ascending keys sort patches by ``(i, j, k)``. At the default 2.3 x 1.0 x 0.7 m this spans
+-4,800 km of easting, +-16,700 km of northing (UTM's false northing included) and +-22 km of height.
Finer grids on large coordinates can set ``anchor_m`` (a fixed world point, part of the config, so ids
stay stable) instead of running out of bits; :meth:`PatchGrid.pack` raises a clear error otherwise.

Worked example::

    >>> g = PatchGrid((2.3, 1.0, 0.7), tile_size_m=100.0)
    >>> ijk = g.cells_world(np.array([[589_001.0, 2_712_000.5, 14.2]]))
    >>> ijk.tolist(), g.tile_of_cells(ijk).tolist()
    ([[256087, 2712000, 20]], [[5890, 27120]])
    >>> g.unpack(g.pack(ijk)).tolist()
    [[256087, 2712000, 20]]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BITS = (22, 25, 16)  # i, j, k
_BIAS = np.array([1 << (b - 1) for b in BITS], dtype=np.int64)
_MASK = np.array([(1 << b) - 1 for b in BITS], dtype=np.int64)
_SHIFT = (BITS[1] + BITS[2], BITS[2], 0)


class GridRangeError(ValueError):
    """Coordinates that are NaN/inf or beyond the packable range of the grid."""


@dataclass(frozen=True)
class PatchGrid:
    """Sizes and anchor of the global patch grid and the ground tiles.

    size_m: (3,) patch edge lengths, metres (paper: 23 x 10 x 7, read as metres x 0.1 = 2.3 x 1.0 x 0.7).
    tile_size_m: ground tile edge, metres (default 100).
    anchor_m: (3,) world point of the corner of cell (0, 0, 0), metres (default the CRS origin).
    """

    size_m: tuple[float, float, float] = (2.3, 1.0, 0.7)
    tile_size_m: float = 100.0
    anchor_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self):
        size = tuple(float(v) for v in np.asarray(self.size_m, dtype=np.float64).reshape(3))
        if not min(size) > 0:
            raise ValueError(f"patch sizes must be positive, got {list(size)}")
        if not float(self.tile_size_m) > 0:
            raise ValueError(f"tile_size_m must be positive, got {self.tile_size_m}")
        object.__setattr__(self, "size_m", size)
        object.__setattr__(self, "tile_size_m", float(self.tile_size_m))
        object.__setattr__(self, "anchor_m", tuple(float(v) for v in np.asarray(self.anchor_m, np.float64).reshape(3)))

    @property
    def size(self) -> np.ndarray:
        return np.asarray(self.size_m, dtype=np.float64)

    @property
    def anchor(self) -> np.ndarray:
        return np.asarray(self.anchor_m, dtype=np.float64)

    # ---------------------------------------------------------------------------------- cells

    def _axis_cells(self, c: np.ndarray, axis: int, offset: float, out: np.ndarray) -> None:
        q = np.asarray(c, dtype=np.float64) + (offset - self.anchor_m[axis])
        np.divide(q, self.size_m[axis], out=q)
        np.floor(q, out=q)
        if q.size:
            lo, hi = q.min(), q.max()  # NaN propagates into both comparisons
            if not (lo >= -_BIAS[axis] and hi < _BIAS[axis]):
                raise GridRangeError(
                    f"{'xyz'[axis]} cells span [{lo}, {hi}]: coordinates are NaN/inf or beyond the "
                    f"+-{int(_BIAS[axis]):,} cells of the grid (wrong units? set partition.grid_anchor_m)")
        out[:] = q

    def cells(self, x: np.ndarray, y: np.ndarray, z: np.ndarray, origin) -> np.ndarray:
        """Cell of each point given campus-local coordinates and the campus origin.

        x, y, z: (n,) float32/float64 metres, campus-local; origin: (3,) float64 world metres.
        Returns (n, 3) int64 world-anchored cells (column-major: each axis contiguous).
        """
        o = np.asarray(origin, dtype=np.float64).reshape(3)
        out = np.empty((len(x), 3), dtype=np.int64, order="F")
        for axis, c in enumerate((x, y, z)):
            self._axis_cells(c, axis, o[axis], out[:, axis])
        return out

    def cells_local(self, xyz: np.ndarray, origin) -> np.ndarray:
        """(n, 3) campus-local metres + (3,) origin -> (n, 3) int64 cells."""
        xyz = np.asarray(xyz)
        if xyz.ndim != 2 or xyz.shape[1] != 3:
            raise ValueError(f"xyz must be (n, 3), got {xyz.shape}")
        return self.cells(xyz[:, 0], xyz[:, 1], xyz[:, 2], origin)

    def cells_world(self, xyz_world: np.ndarray) -> np.ndarray:
        """(n, 3) float64 world metres -> (n, 3) int64 cells."""
        return self.cells_local(xyz_world, (0.0, 0.0, 0.0))

    def face_cells(self, corners: list, origin) -> np.ndarray:
        """Cell of each face centroid (Algorithm 1). corners: the nine (m,) columns x0, y0, z0, x1, ...
        z2 (campus-local metres); the centroid is summed in float64 so every caller gets identical
        cells. Returns (m, 3) int64."""
        c = [np.asarray(v, dtype=np.float64) for v in corners]
        return self.cells((c[0] + c[3] + c[6]) / 3.0, (c[1] + c[4] + c[7]) / 3.0, (c[2] + c[5] + c[8]) / 3.0,
                          origin)

    # ---------------------------------------------------------------------------------- keys

    @staticmethod
    def pack(ijk: np.ndarray) -> np.ndarray:
        """(n, 3) int cells -> (n,) int64 keys; ascending keys order cells by (i, j, k)."""
        ijk = np.asarray(ijk)
        if ijk.ndim != 2 or ijk.shape[1] != 3:
            raise ValueError(f"ijk must be (n, 3), got {ijk.shape}")
        out = np.zeros(len(ijk), dtype=np.int64)
        for a in range(3):  # per axis, in place: no (n, 3) temporaries
            b = ijk[:, a].astype(np.int64)
            b += _BIAS[a]
            if b.size and (b.min() < 0 or b.max() > _MASK[a]):
                raise GridRangeError(f"cells beyond the packable range +-{_BIAS.tolist()} (i, j, k)")
            b <<= _SHIFT[a]
            out |= b
        return out

    @staticmethod
    def unpack(keys: np.ndarray) -> np.ndarray:
        """(n,) int64 keys -> (n, 3) int64 cells (inverse of :meth:`pack`)."""
        keys = np.asarray(keys, dtype=np.int64).reshape(-1)
        out = np.empty((len(keys), 3), dtype=np.int64)
        for a in range(3):
            out[:, a] = ((keys >> _SHIFT[a]) & _MASK[a]) - _BIAS[a]
        return out

    def keys_local(self, xyz: np.ndarray, origin) -> np.ndarray:
        """(n, 3) campus-local metres -> (n,) int64 keys of the containing patches."""
        return self.pack(self.cells_local(xyz, origin))

    # ---------------------------------------------------------------------------------- geometry

    def lower_world(self, ijk: np.ndarray) -> np.ndarray:
        """(n, 3) cells -> (n, 3) float64 world metres of each cell's minimum corner."""
        return np.asarray(ijk, dtype=np.float64) * self.size + self.anchor

    def bounds_local(self, ijk: np.ndarray, origin) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) cells -> ((n, 3) lo, (n, 3) hi) float64 campus-local metres."""
        lo = self.lower_world(ijk) - np.asarray(origin, dtype=np.float64).reshape(3)
        return lo, lo + self.size

    def centre_world(self, ijk: np.ndarray) -> np.ndarray:
        """(n, 3) cells -> (n, 3) float64 world metres of the cell centres."""
        return (np.asarray(ijk, dtype=np.float64) + 0.5) * self.size + self.anchor

    def tile_of_cells(self, ijk: np.ndarray) -> np.ndarray:
        """(n, 3) cells -> (n, 2) int64 tile (ix, iy) holding each cell's centre."""
        c = (np.asarray(ijk, dtype=np.float64)[:, :2] + 0.5) * self.size[:2]
        return np.floor(c / self.tile_size_m).astype(np.int64)

    def tile_of_keys(self, keys: np.ndarray) -> np.ndarray:
        """(n,) int64 keys -> (n, 2) int64 tiles."""
        return self.tile_of_cells(self.unpack(keys))

    def tiles_for_bounds(self, lo, hi, margin_m: float = 0.0) -> np.ndarray:
        """(k, 2) int64 tiles meeting the x/y box [lo, hi] (world metres) grown by ``margin_m``."""
        a = np.floor((np.asarray(lo, np.float64)[:2] - margin_m - self.anchor[:2]) / self.tile_size_m).astype(np.int64)
        b = np.floor((np.asarray(hi, np.float64)[:2] + margin_m - self.anchor[:2]) / self.tile_size_m).astype(np.int64)
        ii, jj = np.meshgrid(np.arange(a[0], b[0] + 1), np.arange(a[1], b[1] + 1), indexing="ij")
        return np.stack([ii.ravel(), jj.ravel()], axis=1)

    def tile_bounds_world(self, ix: int, iy: int) -> tuple[np.ndarray, np.ndarray]:
        """x/y box of tile (ix, iy): ((2,) lo, (2,) hi) world metres."""
        lo = np.array([ix, iy], dtype=np.float64) * self.tile_size_m + self.anchor[:2]
        return lo, lo + self.tile_size_m

    def to_json(self) -> dict:
        return {"size_m": list(self.size_m), "tile_size_m": self.tile_size_m, "anchor_m": list(self.anchor_m)}
