"""The campus frame from the scanned inputs: origin, CRS, and the checks that must hold before anything
is ingested (a projected CRS, point clouds and meshes that overlap). Pure: records in, frame out.
"""

from __future__ import annotations

import numpy as np

from storage.errors import InputError
from storage.frame import CampusFrame
from storage.inputs.identity import InputFile
from tasks.config import CampusConfig
from tasks.scan.extent import clip_point_records, points_box

ORIGIN_SNAP_M = 1000.0  # the origin moves only when the campus crosses a kilometre line


def choose_origin(records: list[InputFile], fixed=None) -> tuple[float, float, float]:
    """The campus origin: ``fixed`` (config), else the minimum x/y corner of every known input extent
    snapped down to :data:`ORIGIN_SNAP_M`, z = 0. A function of the inputs only, so a clean run and a
    resumed run agree."""
    if fixed is not None:
        return tuple(float(v) for v in fixed)
    los = [r.lo for r in records if r.bounded]
    if not los:
        raise InputError(None, "no input could be read (every mesh and point-cloud file failed; see above)")
    lo = np.min(np.asarray(los, np.float64)[:, :2], axis=0)
    o = np.floor(lo / ORIGIN_SNAP_M) * ORIGIN_SNAP_M
    return float(o[0]), float(o[1]), 0.0


def resolve_crs(configured: str | None, point_recs: list[InputFile]) -> str | None:
    """The configured CRS, else the one the inputs agree on (LAS headers, production metadata.xml);
    disagreement is an input error."""
    found = {r.crs for r in point_recs if r.crs and not r.error}
    if configured:
        for r in point_recs:
            if r.crs and r.crs != configured and not r.error:
                raise InputError(r.path, f"CRS {r.crs} in the file disagrees with the configured {configured}: "
                                         "reproject the file or fix inputs.crs")
        return configured
    if len(found) > 1:
        raise InputError(None, f"the inputs carry different CRSs {sorted(found)}: set inputs.crs or reproject")
    return found.pop() if found else None


def check_crs_is_projected(crs: str | None) -> None:
    """A geographic CRS (degrees) cannot be partitioned in metres: say so before anything is read."""
    if not crs:
        return
    try:
        from pyproj import CRS

        c = CRS.from_user_input(crs)
    except Exception as e:  # noqa: BLE001 - pyproj raises several types for a bad string
        raise InputError(None, f"unknown CRS {crs!r} ({e}); give e.g. inputs.crs: EPSG:32650") from None
    horizontal = c.sub_crs_list[0] if c.is_compound and c.sub_crs_list else c
    if horizontal.is_geographic:
        raise InputError(None, f"CRS {crs} is geographic (degrees): ms3d needs a projected CRS in metres "
                               "(e.g. the UTM zone of the campus); reproject the inputs")


def check_overlap(records: list[InputFile], margin_m: float = 50.0) -> None:
    """Raise InputError naming both extents when the point clouds and the meshes do not overlap at all."""
    def box(kind):
        rs = [r for r in records if r.kind == kind and r.bounded and not r.error]
        if not rs:
            return None
        lo = np.min([r.lo for r in rs], axis=0)
        hi = np.max([r.hi for r in rs], axis=0)
        return lo, hi

    pts, mesh = box("points"), box("mesh")
    if pts is None or mesh is None:
        return
    sep = np.maximum(pts[0][:2] - mesh[1][:2], mesh[0][:2] - pts[1][:2])
    if (sep > margin_m).any():
        fmt = lambda b: f"x {b[0][0]:,.0f}..{b[1][0]:,.0f}, y {b[0][1]:,.0f}..{b[1][1]:,.0f}"
        raise InputError(None, f"the point clouds ({fmt(pts)}) and the meshes ({fmt(mesh)}) do not overlap "
                               f"(they are {float(sep.max()):,.0f} m apart): wrong CRS or zone, units, or "
                               "inputs.mesh_offset")


def campus_frame(records: list[InputFile], cfg: CampusConfig) -> CampusFrame:
    """Frame of the campus from the scanned records, point extents clipped to ``inputs.points_bounds``: checks
    CRS, overlap and the float32 reach."""
    check_crs_is_projected(cfg.inputs.crs)
    crs = resolve_crs(cfg.inputs.crs, [r for r in records if r.kind == "points" or r.crs])
    check_crs_is_projected(crs)
    used = clip_point_records(records, points_box(records, cfg.inputs.points_bounds, cfg.grid()))
    check_overlap(used)
    return CampusFrame(origin=choose_origin(used, cfg.inputs.origin), crs=crs)
