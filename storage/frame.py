"""The campus frame: a float64 world origin plus float32 local offsets.

World coordinates (e.g. UTM easting ~500,000 m, northing ~5,000,000 m) do not fit float32 at
millimetre resolution (float32 has ~7 significant digits). Every array inside ms3d is stored as
float32 offsets from a float64 origin; within +-2 km of the origin float32 resolves ~0.12 mm. The
origin is added back only on export.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from storage.errors import InputError

MAX_LOCAL_EXTENT_M = 2000.0  # beyond this, float32 spacing exceeds ~0.12 mm


@dataclass(frozen=True)
class CampusFrame:
    """origin: (3,) float64 metres in ``crs``; crs: e.g. "EPSG:32650" or None when unknown."""

    origin: tuple[float, float, float]
    crs: str | None = None
    units: str = "metre"
    vertical_datum: str | None = None
    extra: dict = field(default_factory=dict, compare=False)

    @property
    def origin_array(self) -> np.ndarray:
        return np.asarray(self.origin, dtype=np.float64)

    def to_local(self, world: np.ndarray, source: str | None = None) -> np.ndarray:
        """world: (n, 3) float64 metres -> (n, 3) float32 metres relative to origin.

        Raises InputError (naming ``source``) for NaN/inf or points too far from the origin for
        float32 at sub-millimetre resolution.
        """
        world = np.asarray(world, dtype=np.float64)
        local = world - self.origin_array
        if local.size:
            if not np.isfinite(local).all():
                bad = int((~np.isfinite(local).all(axis=1)).sum())
                raise InputError(source, f"{bad} coordinates are NaN or infinite")
            reach = float(np.abs(local[:, :2]).max())
            if reach > MAX_LOCAL_EXTENT_M * 5:
                raise InputError(
                    source,
                    f"coordinates lie {reach:,.0f} m from the campus origin {self.origin}: wrong CRS, units "
                    "or a mismatched extent (inputs must overlap the campus)",
                )
        return local.astype(np.float32)

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """local: (n, 3) float32/float64 -> (n, 3) float64 world metres."""
        return np.asarray(local, dtype=np.float64) + self.origin_array

    def to_json(self) -> dict:
        return {
            "origin": list(map(float, self.origin)),
            "crs": self.crs,
            "units": self.units,
            "vertical_datum": self.vertical_datum,
        }

    @classmethod
    def from_json(cls, d: dict) -> CampusFrame:
        return cls(
            origin=tuple(float(v) for v in d["origin"]),
            crs=d.get("crs"),
            units=d.get("units", "metre"),
            vertical_datum=d.get("vertical_datum"),
        )

    @classmethod
    def around(cls, world: np.ndarray, crs: str | None = None, snap_m: float = 100.0) -> CampusFrame:
        """A frame whose origin is the (snapped) minimum corner of the x/y extent and z = 0."""
        world = np.asarray(world, dtype=np.float64)
        lo = np.nanmin(world[:, :2], axis=0)
        o = np.floor(lo / snap_m) * snap_m
        return cls(origin=(float(o[0]), float(o[1]), 0.0), crs=crs)
