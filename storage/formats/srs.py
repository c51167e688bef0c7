"""The SRS a production names (ContextCapture ``metadata.xml`` or a 3MX scene layer), and local ENU frames.

A production's SRS is one of:

- ``EPSG:<code>`` or a compound ``EPSG:<h>+<v>``: kept as written (upper case);
- a WKT (``PROJCS[...]``, ``PROJCRS[...]``, ``COMPD_CS[...]``, ``COMPOUNDCRS[...]``): read with pyproj and
  named by the EPSG code it identifies with (``EPSG:<h>+<v>`` for a compound one). A geographic or
  geocentric WKT (degrees, or not a map) and a WKT with no EPSG equivalent are refused;
- ``ENU:<lat>,<lon>``: a local east-north-up frame tangent to the WGS 84 ellipsoid at (lat, lon, height
  0), metres (ContextCapture's "local" productions). Its vertices are placed into the campus CRS
  (``inputs.crs``) by :func:`enu_to_crs`: east/north/up -> ECEF (exact) -> the CRS with PROJ.

Anything else is refused with one line naming the file.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.errors import InputError

_EPSG = re.compile(r"^EPSG:\d+(\+\d+)?$", re.IGNORECASE)
_NUM = r"[-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?"
_ENU = re.compile(rf"^ENU:\s*(?P<lat>{_NUM})\s*,\s*(?P<lon>{_NUM})\s*$", re.IGNORECASE)
_WKT_HEAD = ("PROJCS[", "PROJCRS[", "PROJECTEDCRS[", "COMPD_CS[", "COMPOUNDCRS[", "GEOGCS[", "GEOGCRS[",
             "GEODCRS[", "GEOCCS[", "BOUNDCRS[")
WGS84_A, WGS84_F = 6378137.0, 1 / 298.257223563


@dataclass(frozen=True)
class Srs:
    """A parsed SRS. name: "EPSG:<code>[+<code>]" or "ENU:<lat>,<lon>"; enu: (lat, lon) degrees of a local
    ENU frame's tangent point, None for a map CRS."""

    name: str
    enu: tuple[float, float] | None = None


def _short(text: str) -> str:
    return text if len(text) <= 60 else text[:57] + "..."


def _refuse(path, text: str, why: str) -> InputError:
    return InputError(path, f"unknown SRS {_short(text)!r}: {why}; ms3d reads EPSG:<code>, a projected WKT or "
                            "ENU:<lat>,<lon>")


def _from_wkt(text: str, path) -> Srs:
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        crs = CRS.from_wkt(text)
    except CRSError:
        raise _refuse(path, text, "not a readable WKT") from None
    parts = crs.sub_crs_list if crs.is_compound else [crs]
    if not parts[0].is_projected:
        kind = "geographic (degrees)" if parts[0].is_geographic else "not a projected CRS"
        raise _refuse(path, text, f"the WKT is {kind}")
    codes = []
    for part in parts:
        code = part.to_epsg(min_confidence=70)
        if code is None:
            raise _refuse(path, text, f"the WKT's {part.name!r} has no EPSG equivalent")
        codes.append(str(code))
    return Srs("EPSG:" + "+".join(codes))


def parse_srs(text: str, path: str | Path) -> Srs:
    """Parse a production's SRS (module doc). path: the file that names it (for the error). Raises
    InputError naming ``path`` for an empty or unusable SRS."""
    s = (text or "").strip()
    if not s:
        raise InputError(path, "no SRS: the production cannot be georeferenced")
    if _EPSG.match(s):
        return Srs(s.upper())
    m = _ENU.match(s)
    if m:
        lat, lon = float(m["lat"]), float(m["lon"])
        if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0):
            raise _refuse(path, s, f"ENU tangent point latitude {lat} / longitude {lon} out of range")
        return Srs(f"ENU:{lat:.9g},{lon:.9g}", (lat, lon))
    if s.upper().startswith(_WKT_HEAD):
        return _from_wkt(s, path)
    raise _refuse(path, s, "not an EPSG code, a WKT or an ENU frame")


def geodetic_to_ecef(lat_deg: float, lon_deg: float, h: float = 0.0) -> np.ndarray:
    """(3,) float64 ECEF metres of a WGS 84 geodetic point.

    >>> geodetic_to_ecef(0.0, 0.0).round(3).tolist()
    [6378137.0, 0.0, 0.0]
    """
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    e2 = WGS84_F * (2 - WGS84_F)
    n = WGS84_A / np.sqrt(1 - e2 * np.sin(la) ** 2)
    return np.array([(n + h) * np.cos(la) * np.cos(lo), (n + h) * np.cos(la) * np.sin(lo),
                     (n * (1 - e2) + h) * np.sin(la)])


def enu_axes(lat_deg: float, lon_deg: float) -> np.ndarray:
    """(3, 3) float64: rows are the east, north and up unit vectors in ECEF at (lat, lon)."""
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    return np.array([[-np.sin(lo), np.cos(lo), 0.0],
                     [-np.sin(la) * np.cos(lo), -np.sin(la) * np.sin(lo), np.cos(la)],
                     [np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)]])


def enu_to_crs(enu: np.ndarray, lat_deg: float, lon_deg: float, crs: str, geoid_spec: str | None = None,
               chunk: int = 1 << 20) -> np.ndarray:
    """Place local ENU coordinates into a projected CRS. enu: (n, 3) float64 metres east/north/up of the
    WGS 84 tangent point (lat, lon, 0); crs: the target. ENU -> ECEF is exact; ECEF -> ``crs`` is
    :func:`ecef_to_crs` (heights made orthometric with a geoid where the CRS's vertical datum needs one PROJ
    lacks). Returns (n, 3) float64. Raises ValueError when PROJ cannot transform into ``crs``."""
    origin, axes = geodetic_to_ecef(lat_deg, lon_deg), enu_axes(lat_deg, lon_deg)
    return ecef_to_crs(origin + np.asarray(enu, np.float64).reshape(-1, 3) @ axes, crs, geoid_spec, chunk)


def ecef_to_crs(ecef: np.ndarray, crs: str, geoid_spec: str | None = None, chunk: int = 1 << 20) -> np.ndarray:
    """ECEF metres (n, 3) -> ``crs`` (n, 3) float64 (x, y and the CRS's height). Where PROJ has no geoid
    grid for the CRS's vertical datum (a ballpark vertical step), heights are made orthometric with the
    geoid of ``geoid_spec`` (:func:`storage.geoid.geoid_of`: None = the shipped EGM96), H = h - N: the inverse
    of the export's georeferencing. Raises ValueError when PROJ cannot transform into ``crs``."""
    from pyproj import CRS, Transformer

    from storage.geoid import geoid_of

    dst = CRS.from_user_input(crs)
    if not dst.is_compound:
        if not dst.is_projected:
            raise ValueError(f"{crs} is not a projected CRS in metres")
        dst = dst.to_3d()
    tr = Transformer.from_crs("EPSG:4978", dst, always_xy=True)
    ballpark = "ballpark vertical" in tr.description.lower() or "without ellipsoid height" in tr.description.lower()
    geo = Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True) if ballpark else None
    geoid = geoid_of(geoid_spec) if ballpark else None
    ecef = np.asarray(ecef, np.float64).reshape(-1, 3)
    out = np.empty_like(ecef)
    for i in range(0, len(ecef), chunk):
        e = ecef[i:i + chunk]
        x, y, z = tr.transform(e[:, 0], e[:, 1], e[:, 2])
        z = np.asarray(z, np.float64)
        if geo is not None:
            lon, lat, _ = geo.transform(e[:, 0], e[:, 1], e[:, 2])
            z = z - geoid.undulation(np.asarray(lat), np.asarray(lon))
        out[i:i + chunk] = np.column_stack([x, y, z])
    if not np.isfinite(out).all():
        raise ValueError(f"PROJ could not place ECEF coordinates into {crs}")
    return out


__all__ = ["Srs", "ecef_to_crs", "enu_axes", "enu_to_crs", "geodetic_to_ecef", "parse_srs"]
