"""Value types naming the units of work: tiles and patches (a region is named by its key:
:class:`storage.contracts.region_plan.Region`).

They are frozen dataclasses with a ``key`` used in paths and manifest rows.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, order=True)
class TileId:
    """A cell of the ground tile grid (default 100 m): tile (ix, iy) covers
    ``[ix*size, (ix+1)*size) x [iy*size, (iy+1)*size)`` in world x/y metres (projected CRS), so a tile
    keeps its key whatever the campus extent (see :class:`storage.grid.PatchGrid`)."""

    ix: int
    iy: int

    @property
    def key(self) -> str:
        return f"{self.ix}_{self.iy}"

    @classmethod
    def from_key(cls, key: str) -> TileId:
        ix, iy = key.split("_")
        return cls(int(ix), int(iy))


@dataclass(frozen=True, order=True)
class PatchId:
    """A cell (i, j, k) of the global, world-anchored 3D patch grid (default 2.3 x 1.0 x 0.7 m)."""

    i: int
    j: int
    k: int

    @property
    def key(self) -> str:
        return f"{self.i}_{self.j}_{self.k}"
