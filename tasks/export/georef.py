"""Georeferencing for export: campus-local projected coordinates -> a local east-north-up frame.

A projected grid (UTM, RD New) is not ENU: grid convergence and scale error move points by up to tens of
metres at 1 km from the origin, so every vertex goes projected (float64 world = origin + local) -> ECEF
(EPSG:4978) -> ENU in float64 with pyproj, and only the ENU result is cast to float32. The tileset's root
``transform`` is the float64 ENU->ECEF matrix.

Heights: ECEF needs ellipsoidal heights. A compound CRS (e.g. EPSG:7415 = RD New + NAP height) is passed to
PROJ whole; when the geoid grid it needs is installed, PROJ's operation applies it. When it is not (none can
be downloaded here), PROJ's best operation is a "ballpark" vertical step that takes orthometric heights as
ellipsoidal; ms3d then adds the geoid undulation itself (:class:`GeoidCorrected`): from the user's grid
(``export.geoid_grid``, a PROJ vertical grid file) or else from the EGM96 geoid it ships
(:mod:`storage.geoid`), along the ellipsoid normal, h = H + N. A 2D projected CRS gets ellipsoidal heights of
its own datum (``CRS.to_3d``); a ``vertical_datum`` of the form "EPSG:nnnn" (a vertical CRS) is composed
with it. The operation and whatever was assumed are recorded in ``georef.json``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np

ECEF_CRS = "EPSG:4978"
GEODETIC_3D_CRS = "EPSG:4979"


@dataclass(frozen=True, eq=False)
class GeoRef:
    """A local ENU frame at ``enu_origin_local`` (campus-local metres) and the operation that gets there.

    frame_origin: (3,) float64 world origin of the campus frame, in ``source_crs``.
    enu_origin_local: (3,) float64 campus-local point that is ENU (0, 0, 0).
    lon_deg, lat_deg, height_m: its WGS 84 geodetic position (ellipsoidal height).
    ecef_origin: (3,) float64 metres. enu_to_ecef: (4, 4) float64 (row-major here; ``tileset_transform``
    gives the column-major list 3D Tiles wants).
    operation: PROJ's description of the operation used; assumptions: sentences for ``georef.json``.
    """

    source_crs: str
    vertical_datum: str | None
    frame_origin: tuple[float, float, float]
    enu_origin_local: tuple[float, float, float]
    lon_deg: float
    lat_deg: float
    height_m: float
    ecef_origin: tuple[float, float, float]
    enu_to_ecef: np.ndarray
    operation: str
    assumptions: list[str] = field(default_factory=list)
    geoid: str | None = None  # storage.geoid.geoid_of spec of the geoid ms3d applied (None: PROJ's op alone)

    @property
    def ecef_to_enu_rotation(self) -> np.ndarray:
        """(3, 3) float64 R with enu = R @ (ecef - ecef_origin)."""
        return self.enu_to_ecef[:3, :3].T

    def tileset_transform(self) -> list[float]:
        """The 16 numbers of ``enu_to_ecef`` in column-major order (3D Tiles ``transform``)."""
        return [float(v) for v in self.enu_to_ecef.T.reshape(-1)]

    def to_json(self) -> dict:
        return {
            "source_crs": self.source_crs,
            "vertical_datum": self.vertical_datum,
            "frame_origin": list(self.frame_origin),
            "enu_origin_local": list(self.enu_origin_local),
            "enu_origin_world": [o + e for o, e in zip(self.frame_origin, self.enu_origin_local)],
            "enu_origin_wgs84": {"lon_deg": self.lon_deg, "lat_deg": self.lat_deg, "ellipsoidal_height_m": self.height_m},
            "ecef_origin": list(self.ecef_origin),
            "enu_to_ecef_column_major": self.tileset_transform(),
            "gltf_axes": "glTF y-up: (x, y, z)_gltf = (east, up, -north); 3D Tiles rotates y-up to z-up",
            "operation": self.operation,
            "geoid": self.geoid,
            "assumptions": list(self.assumptions),
        }  # fmt: skip


def enu_rotation(lon_deg: float, lat_deg: float) -> np.ndarray:
    """(3, 3) float64 rows = east, north, up unit vectors in ECEF at (lon, lat).

    >>> (np.round(enu_rotation(0.0, 0.0), 12) + 0.0).tolist()
    [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]
    """
    lo, la = np.radians(lon_deg), np.radians(lat_deg)
    return np.array([
        [-np.sin(lo), np.cos(lo), 0.0],
        [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
        [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)],
    ])  # fmt: skip


def _source_crs_3d(crs: str, vertical_datum: str | None):
    """The pyproj CRS to transform from, and the assumptions that choice makes."""
    from pyproj import CRS
    from pyproj.crs import CompoundCRS

    src = CRS.from_user_input(crs)
    notes = []
    if src.is_compound:
        vert = [s for s in src.sub_crs_list if s.is_vertical]
        notes.append(f"heights are in {vert[0].name if vert else 'the vertical CRS of ' + src.name}")
        return src, notes
    if src.is_geocentric:
        raise ValueError(f"{crs}: a geocentric CRS is not a campus CRS")
    vd = (vertical_datum or "").strip()
    if vd.upper().startswith("EPSG:"):
        vcrs = CRS.from_user_input(vd)
        if vcrs.is_vertical:
            notes.append(f"heights are in {vcrs.name} ({vd}), composed with {src.name}")
            return CompoundCRS(f"{src.name} + {vcrs.name}", [src, vcrs]), notes
    if src.is_projected or src.is_geographic:
        three_d = src.to_3d()
        if vd and "ellipsoid" not in vd.lower():
            notes.append(f"vertical datum {vd!r} is not a vertical CRS code: its heights are taken as ellipsoidal "
                         f"heights of {src.geodetic_crs.name} (off by the local geoid undulation)")
        else:
            notes.append(f"heights are ellipsoidal heights of {src.geodetic_crs.name}")
        return three_d, notes
    return src, notes


def _choose_operation(src, lon_lat: tuple[float, float] | None):
    """The best operation to ECEF that PROJ can run offline, never a 'ballpark geographic offset' when a
    real datum shift is available. Returns (Transformer, assumptions)."""
    from pyproj.aoi import AreaOfInterest
    from pyproj.transformer import TransformerGroup

    aoi = None
    if lon_lat is not None:
        lo, la = lon_lat
        aoi = AreaOfInterest(lo - 0.01, la - 0.01, lo + 0.01, la + 0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the missing grid is reported in the assumptions instead
        group = TransformerGroup(src, ECEF_CRS, always_xy=True, area_of_interest=aoi)
    if not group.transformers:
        raise ValueError(f"PROJ has no operation from {src.name} to {ECEF_CRS} that runs offline")
    real = [t for t in group.transformers if "allpark geographic offset" not in t.description]
    chosen = (real or group.transformers)[0]
    notes = []
    if group.unavailable_operations:
        grids = sorted({g.short_name for op in group.unavailable_operations for g in op.grids if not g.available})
        notes.append(f"better operations need grids not installed here ({', '.join(grids)}); used: {chosen.description}")
    if "ballpark vertical" in chosen.description.lower() or "without ellipsoid height" in chosen.description.lower():
        notes.append("no geoid model offline: orthometric heights are treated as ellipsoidal heights "
                     "(the model sits off the ellipsoid by the geoid undulation; its shape is unaffected)")
    if not real:
        notes.append("only a ballpark geographic offset is available: horizontal position may be off by ~100 m")
    return chosen, notes


def _is_ballpark_vertical(description: str) -> bool:
    d = description.lower()
    return "ballpark vertical" in d or "without ellipsoid height" in d


class GeoidCorrected:
    """A PROJ operation to ECEF that took orthometric heights as ellipsoidal (a ballpark vertical step),
    corrected by a geoid: each point moves N(lat, lon) metres along the ellipsoid normal (h = H + N).
    ``transform(x, y, z)`` as a pyproj Transformer's (scalars or arrays); ``description`` names both."""

    def __init__(self, inner, geoid):
        from pyproj import Transformer

        self.inner, self.geoid = inner, geoid
        self._geodetic = Transformer.from_crs(ECEF_CRS, GEODETIC_3D_CRS, always_xy=True)
        self.description = f"{inner.description} + heights made ellipsoidal with the {geoid.name}"

    def transform(self, x, y, z):
        scalar = np.ndim(x) == 0
        ex, ey, ez = (np.atleast_1d(np.asarray(v, np.float64)) for v in self.inner.transform(x, y, z))
        lon, lat, _ = self._geodetic.transform(ex, ey, ez)
        n = self.geoid.undulation(np.asarray(lat), np.asarray(lon))
        la, lo = np.radians(lat), np.radians(lon)
        ex, ey, ez = ex + n * np.cos(la) * np.cos(lo), ey + n * np.cos(la) * np.sin(lo), ez + n * np.sin(la)
        return (float(ex[0]), float(ey[0]), float(ez[0])) if scalar else (ex, ey, ez)


def _with_geoid(src, to_ecef, notes: list[str], geoid_grid: str | None):
    """(operation, notes, geoid spec): ``to_ecef`` corrected by a geoid when it treats orthometric heights as
    ellipsoidal; else unchanged (a configured grid is then not needed, and the notes say so)."""
    from storage.geoid import geoid_of

    if not _is_ballpark_vertical(to_ecef.description):
        if geoid_grid:
            notes = notes + [f"export.geoid_grid {geoid_grid} not used: PROJ's operation applies its own geoid"]
        return to_ecef, notes, None
    geoid = geoid_of(geoid_grid)
    vert = [c for c in (src.sub_crs_list if src.is_compound else [src]) if c.is_vertical]
    vname = vert[0].name if vert else "the vertical CRS"
    notes = [n for n in notes if "treated as ellipsoidal" not in n]
    notes.append(f"orthometric heights ({vname}) made ellipsoidal with the {geoid.name}: h = H + N")
    if geoid.spec == "egm96" and "egm96" not in vname.lower():
        notes.append(f"EGM96 stands in for the geoid model of {vname} (its grid is not installed; name one in "
                     "export.geoid_grid): heights may be off by the difference of the two geoids, typically "
                     "decimetres, up to about a metre")
    return GeoidCorrected(to_ecef, geoid), notes, geoid.spec


def make_georef(crs: str, frame_origin, enu_origin_local, vertical_datum: str | None = None,
                geoid_grid: str | None = None) -> GeoRef:
    """A GeoRef with ENU origin at campus-local ``enu_origin_local`` (e.g. the campus centre on the ground).

    crs: the campus CRS ("EPSG:32650", "EPSG:7415", ...); frame_origin: (3,) float64 world metres of the
    campus frame; enu_origin_local: (3,) float64 campus-local metres; geoid_grid: a PROJ vertical grid file
    for orthometric heights when PROJ has none of its own (None: the shipped EGM96; module doc).
    """
    from pyproj import Transformer

    src, notes = _source_crs_3d(crs, vertical_datum)
    origin = np.asarray(frame_origin, np.float64)
    centre_world = origin + np.asarray(enu_origin_local, np.float64)
    to_geodetic = Transformer.from_crs(src, GEODETIC_3D_CRS, always_xy=True)
    lon_guess, lat_guess, _ = to_geodetic.transform(*centre_world)
    to_ecef, more = _choose_operation(src, (lon_guess, lat_guess) if np.isfinite(lon_guess) else None)
    to_ecef, more, geoid = _with_geoid(src, to_ecef, more, geoid_grid)
    ecef0 = np.array(to_ecef.transform(*centre_world), np.float64)
    if not np.isfinite(ecef0).all():
        raise ValueError(f"{crs}: the campus origin {tuple(centre_world)} is outside the CRS's area of use")
    lon, lat, h = Transformer.from_crs(ECEF_CRS, GEODETIC_3D_CRS, always_xy=True).transform(*ecef0)
    m = np.eye(4)
    m[:3, :3] = enu_rotation(lon, lat).T
    m[:3, 3] = ecef0
    return GeoRef(
        source_crs=str(crs), vertical_datum=vertical_datum, frame_origin=tuple(map(float, origin)),
        enu_origin_local=tuple(map(float, enu_origin_local)), lon_deg=float(lon), lat_deg=float(lat),
        height_m=float(h), ecef_origin=tuple(map(float, ecef0)), enu_to_ecef=m, operation=to_ecef.description,
        assumptions=notes + more, geoid=geoid,
    )  # fmt: skip


class EnuProjector:
    """Maps campus-local coordinates to ECEF / ENU (float64) with the PROJ operation of ``georef``."""

    def __init__(self, georef: GeoRef):
        from storage.geoid import geoid_of

        src, _ = _source_crs_3d(georef.source_crs, georef.vertical_datum)
        self._to_ecef, _ = _choose_operation(src, (georef.lon_deg, georef.lat_deg))  # the one make_georef chose
        if georef.geoid is not None:
            self._to_ecef = GeoidCorrected(self._to_ecef, geoid_of(georef.geoid))
        if self._to_ecef.description != georef.operation:
            raise ValueError(f"PROJ now picks {self._to_ecef.description!r}, the georef used {georef.operation!r}")
        self._origin = np.asarray(georef.frame_origin, np.float64)
        self._ecef0 = np.asarray(georef.ecef_origin, np.float64)
        self._r = georef.ecef_to_enu_rotation

    def local_to_ecef(self, local: np.ndarray) -> np.ndarray:
        """local: (n, 3) float32/64 campus-local metres -> (n, 3) float64 ECEF metres."""
        world = np.asarray(local, np.float64) + self._origin
        x, y, z = self._to_ecef.transform(world[:, 0], world[:, 1], world[:, 2])
        return np.stack([x, y, z], axis=1)

    def local_to_enu(self, local: np.ndarray, chunk: int = 1 << 20) -> np.ndarray:
        """local: (n, 3) campus-local metres -> (n, 3) float64 ENU metres (cast to float32 by the caller)."""
        out = np.empty((len(local), 3), np.float64)
        for lo in range(0, len(local), chunk):  # bounded temporaries
            ecef = self.local_to_ecef(local[lo : lo + chunk])
            out[lo : lo + chunk] = (ecef - self._ecef0) @ self._r.T
        return out


def enu_to_gltf(enu: np.ndarray) -> np.ndarray:
    """(n, 3) ENU (z-up) -> (n, 3) float32 glTF y-up: (e, n, u) -> (e, u, -n).

    >>> enu_to_gltf(np.array([[1.0, 2.0, 3.0]])).tolist()
    [[1.0, 3.0, -2.0]]
    """
    enu = np.asarray(enu)
    return np.stack([enu[:, 0], enu[:, 2], -enu[:, 1]], axis=1).astype(np.float32)


def gltf_to_enu(xyz: np.ndarray) -> np.ndarray:
    """Inverse of ``enu_to_gltf`` (what a 3D Tiles client does for y-up glTF): (x, y, z) -> (x, -z, y)."""
    xyz = np.asarray(xyz, np.float64)
    return np.stack([xyz[:, 0], -xyz[:, 2], xyz[:, 1]], axis=1)
