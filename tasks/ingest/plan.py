"""Ingest's plan: the units (whole mesh files, ranges of point files), how they are batched into task
runs, and which tiles a bad input blocks. Pure: scan records in, units and tile keys out.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from storage.contracts.staging import unit_key
from storage.frame import CampusFrame
from storage.grid import PatchGrid
from storage.inputs.identity import InputFile
from tasks.batches import balanced_batches, fixed_batches
from tasks.geometry.tiling import transform_bounds
from tasks.scan import Box, clip_point_records, file_size, outside_box

LAS_SUFFIXES = (".las", ".laz")

@dataclass(frozen=True)
class IngestUnit:
    """One unit of ingest (JSON-able). start/stop: point range of a LAS/LAZ file (0, 0 otherwise);
    bounds: the x/y box of the points to route (``inputs.points_bounds``), None for every point."""

    key: str
    source: int
    path: str
    kind: str  # "points" | "mesh"
    fingerprint: str
    start: int = 0
    stop: int = 0
    bounds: Box | None = None

    def __post_init__(self):
        if self.bounds is not None:  # a list after a JSON round trip
            object.__setattr__(self, "bounds", tuple(float(v) for v in self.bounds))

    def to_json(self) -> dict:
        return asdict(self)


def plan_units(records: list[InputFile], chunk_points: int, box: Box | None = None) -> list[IngestUnit]:
    """Ingest units of the readable inputs: whole mesh files, ranges of ``chunk_points`` per LAS/LAZ
    file, whole files of other point formats. With a points ``box``, a point file outside it has no unit
    and every point unit carries the box."""
    units = []
    for r in sorted(records, key=lambda r: (r.kind, r.source)):
        if r.error or outside_box(r, box):
            continue
        if r.kind == "mesh":
            units.append(IngestUnit(unit_key("mesh", r.source, r.fingerprint, 0), r.source, r.path, "mesh", r.fingerprint))
        elif Path(r.path).suffix.lower() in LAS_SUFFIXES:
            for c, a in enumerate(range(0, r.count, chunk_points)):
                units.append(IngestUnit(unit_key("points", r.source, r.fingerprint, c), r.source, r.path, "points",
                                        r.fingerprint, a, min(a + chunk_points, r.count), box))
        else:
            units.append(IngestUnit(unit_key("points", r.source, r.fingerprint, 0), r.source, r.path, "points",
                                    r.fingerprint, 0, r.count, box))
    return units


def tiles_hint(rec: InputFile, frame: CampusFrame, matrix: np.ndarray, grid: PatchGrid,
               box: Box | None = None) -> list[str]:
    """Tile keys the file's bounds cover (empty when its extent is unknown or, for points, outside the
    ``box``). Point bounds are clipped to the box, then mapped by the registration."""
    if not rec.bounded or outside_box(rec, box):
        return []
    rec = clip_point_records([rec], box)[0]
    lo, hi = np.asarray(rec.lo, np.float64), np.asarray(rec.hi, np.float64)
    if rec.kind == "points":
        o = frame.origin_array
        lo, hi = transform_bounds(matrix, lo - o, hi - o)
        lo, hi = lo + o, hi + o
    return [f"{i}_{j}" for i, j in grid.tiles_for_bounds(lo, hi, margin_m=1.0).tolist()]


def ingest_batches(units: list[IngestUnit], n_workers: int) -> tuple[list[list[dict]], list[list[dict]]]:
    """(mesh batches, point batches) of unit JSON: meshes in at most ``4 * n_workers`` batches of about
    equal file size (they are routed while registration runs), one point range per batch."""
    meshes = [u for u in units if u.kind == "mesh"]
    mesh_batches = balanced_batches([u.to_json() for u in meshes], [file_size(u.path) for u in meshes],
                                    4 * max(n_workers, 1))
    return mesh_batches, fixed_batches([u.to_json() for u in units if u.kind == "points"], 1)


def input_tiles(records: list[InputFile], frame: CampusFrame, matrix: np.ndarray,
                grid: PatchGrid, box: Box | None = None) -> dict[int, list[str]]:
    """{source id: the tile keys its bounds cover} for every scanned input (:func:`tiles_hint`)."""
    return {r.source: tiles_hint(r, frame, matrix, grid, box) for r in records}


def blocked_tiles(records: list[InputFile], ingests: list[dict], units: list[IngestUnit], frame: CampusFrame,
                  matrix: np.ndarray, grid: PatchGrid,
                  box: Box | None = None) -> tuple[dict[str, str], dict[str, str], list[str]]:
    """What the bad inputs block: a scan error or a failed ingest unit (``ingests``: unit summaries) fails
    its input, which blocks every tile its bounds cover; an input of unknown bounds blocks none and makes
    the campus incomplete, and a point file outside the points ``box`` neither.

    Returns (blocked {tile key: reason}, failed {"input <name>": error}, incomplete [paths]).
    """
    by_source = {r.source: r for r in records}
    hints = input_tiles(records, frame, matrix, grid, box)
    unit_src = {u.key: u.source for u in units}
    bad_inputs = [(r, r.error) for r in records if r.error]
    bad_inputs += [(by_source[unit_src[s["unit"]]], s["error"]) for s in ingests
                   if s["status"] == "failed" and s["unit"] in unit_src]
    blocked: dict[str, str] = {}
    failed: dict[str, str] = {}
    incomplete: list[str] = []
    for r, err in bad_inputs:
        failed[f"input {r.name}"] = err
        if not hints[r.source] and not outside_box(r, box):
            incomplete.append(r.path)
        for tk in hints[r.source]:
            blocked.setdefault(tk, f"blocked: its input {r.name} failed (see that input's error)")
    return blocked, failed, incomplete
