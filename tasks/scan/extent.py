"""The part of the MLS a campus uses: ``inputs.points_bounds`` as an x/y box, and the point-file extents
clipped to it. Pure: scan records in, a box and records out.

A city-wide point cloud (a COPC of a whole district, say) feeds a campus through this box: only its points
inside are ingested (a COPC decompresses only its octree nodes over the box), a file outside it has no
ingest unit and covers no tile, and the campus origin and the overlap check see the clipped extents.
The box is compared with the point files' own world coordinates (after ``inputs.units_scale``, before the
registration, which moves them by centimetres to a metre).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from storage.errors import InputError
from storage.grid import PatchGrid
from storage.inputs.identity import InputFile

Box = tuple[float, float, float, float]  # [xmin, ymin, xmax, ymax] world metres


def points_box(records: list[InputFile], bounds: Box | str | None, grid: PatchGrid) -> Box | None:
    """The x/y box of the MLS points to ingest, from ``inputs.points_bounds``: the config's box; for "mesh"
    the meshes' x/y extent grown by one tile and snapped out to the tile grid (a small change of a mesh
    keeps the box, and so the points' ingest); None: every point (also "mesh" when no mesh has bounds).

    >>> m = InputFile(0, "city.obj", "mesh", "f", lo=[120.0, 30.0, 0.0], hi=[180.0, 90.0, 9.0])
    >>> points_box([m], "mesh", PatchGrid((1.0, 1.0, 1.0), tile_size_m=100.0))
    (0.0, -100.0, 300.0, 200.0)
    """
    if bounds is None or bounds != "mesh":
        return None if bounds is None else tuple(float(v) for v in bounds)
    meshes = [r for r in records if r.kind == "mesh" and r.bounded]
    if not meshes:
        return None
    t, a = grid.tile_size_m, grid.anchor[:2]
    lo = np.floor((np.min([r.lo[:2] for r in meshes], axis=0) - t - a) / t) * t + a
    hi = np.ceil((np.max([r.hi[:2] for r in meshes], axis=0) + t - a) / t) * t + a
    return (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))


def outside_box(rec: InputFile, box: Box | None) -> bool:
    """Whether a point file's known x/y bounds miss ``box`` entirely (it then feeds no tile)."""
    if box is None or rec.kind != "points" or not rec.bounded:
        return False
    return bool(rec.hi[0] < box[0] or rec.lo[0] > box[2] or rec.hi[1] < box[1] or rec.lo[1] > box[3])


def clip_point_records(records: list[InputFile], box: Box | None) -> list[InputFile]:
    """The records with every point file's x/y bounds clipped to ``box`` and the point files outside it left
    out (meshes and files of unknown bounds as they are)."""
    if box is None:
        return list(records)
    out = []
    for r in records:
        if outside_box(r, box):
            continue
        if r.kind == "points" and r.bounded:
            lo, hi = list(r.lo), list(r.hi)
            lo[:2] = [max(lo[0], box[0]), max(lo[1], box[1])]
            hi[:2] = [min(hi[0], box[2]), min(hi[1], box[3])]
            r = replace(r, lo=lo, hi=hi)
        out.append(r)
    return out


def files_outside_box(records: list[InputFile], box: Box | None) -> list[str]:
    """The paths of the readable point files that ``box`` leaves out entirely (the run says so). Raises
    InputError when it leaves out every one of them: a box in another CRS or unit, not a campus without a
    scan.

    >>> a = InputFile(0, "a.laz", "points", "f", lo=[0.0, 0.0, 0.0], hi=[10.0, 10.0, 5.0])
    >>> b = InputFile(1, "b.laz", "points", "g", lo=[500.0, 0.0, 0.0], hi=[510.0, 10.0, 5.0])
    >>> files_outside_box([a, b], (0.0, 0.0, 100.0, 100.0))
    ['b.laz']
    """
    points = [r for r in records if r.kind == "points" and not r.error]
    out = [r.path for r in points if outside_box(r, box)]
    if points and len(out) == len(points):
        lo = np.min([r.lo[:2] for r in points if r.bounded], axis=0)
        hi = np.max([r.hi[:2] for r in points if r.bounded], axis=0)
        raise InputError(None, f"inputs.points_bounds {list(box)} overlaps no MLS point file (theirs span x "
                               f"{lo[0]:.1f}..{hi[0]:.1f}, y {lo[1]:.1f}..{hi[1]:.1f}): a box in another CRS or unit?")
    return out


__all__ = ["Box", "clip_point_records", "files_outside_box", "outside_box", "points_box"]
