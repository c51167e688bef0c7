"""Evidence of a region's defect type, and the repair each type gets (beyond the paper's single repair).

The paper grades a patch good or bad and rebuilds every bad region the same way. A bad region's
mesh is wrong in one of a few ways, and the MLS tells which:

- **hole**: surface the MLS saw where the mesh has none (open boundary loops in the zone, MLS points
  with no mesh vertex near them);
- **protrusion**: mesh vertices in front of the MLS surface they project onto (melted eaves, bumps);
- **recess**: mesh vertices behind it (dents, recesses);
- **misalignment**: the mesh parallel to the MLS surface but offset (warps, a local registration error);
- **uncovered**: the MLS saw (almost) nothing of the region: no evidence; the mesh is all there is.

Repairs by type (:func:`repair_plan`): a region the MLS does not cover is left to the mesh; vertices
that the MLS covers and that stand off its surface (protrusion, recess, misalignment) are forced out
of the fused set (cut back to the MLS surface) instead of being kept because no MLS point is
*similar* to them; holes are filled by the fused points as in the paper.

Frames and units: campus-local metres.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

TYPES = ("hole", "protrusion", "recess", "misalignment", "uncovered")


@dataclass(frozen=True)
class DefectEvidence:
    """Per-region evidence. coverage: fraction of zone vertices whose position the MLS surface covers;
    protrusion / recess: fraction of covered vertices in front of / behind the MLS by > offset;
    median_offset_m, offset_spread_m: median and MAD of the covered vertices' offsets;
    hole_area_m2: MLS surface with no mesh within hole_gap_m (area of one thinned point each);
    open_loop_m: length of the zone's open boundary loops (holes in the mesh); type: the verdict."""

    n_vertices: int
    coverage: float
    protrusion: float
    recess: float
    median_offset_m: float
    offset_spread_m: float
    hole_area_m2: float
    open_loop_m: float
    type: str

    def to_json(self) -> dict:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()}


def classify_evidence(covered: np.ndarray, offset: np.ndarray, *, offset_m: float, hole_area_m2: float,
                      open_loop_m: float, zone_area_m2: float, min_coverage: float) -> DefectEvidence:
    """The evidence of one region and its type.

    covered: (nv,) bool and offset: (nv,) float (NaN where uncovered) from
    :func:`tasks.repair.fuse.coverage_offsets`; zone_area_m2: area of the zone's faces.
    Rule (in this order): coverage below min_coverage -> uncovered; MLS-only surface above 0.5 m² and
    15 % of the zone area -> hole; covered vertices off the surface on both sides (each side over
    15 %, the smaller at least 40 % of the larger: the mesh bends across the surface) -> misalignment;
    more than 20 % in front -> protrusion, behind -> recess; |median offset| > offset_m / 2 with a
    spread below offset_m -> misalignment (a shift); otherwise hole when the zone has open loops, else
    the stronger side.
    """
    nv = len(covered)
    cov = float(covered.mean()) if nv else 0.0
    off = offset[covered]
    front = float((off > offset_m).mean()) if len(off) else 0.0
    back = float((off < -offset_m).mean()) if len(off) else 0.0
    med = float(np.median(off)) if len(off) else float("nan")
    spread = float(np.median(np.abs(off - med))) if len(off) else float("nan")
    if cov < min_coverage:
        t = "uncovered"
    elif hole_area_m2 > max(0.15 * zone_area_m2, 0.5):
        t = "hole"
    elif min(front, back) > 0.15 and min(front, back) >= 0.4 * max(front, back):
        t = "misalignment"
    elif front > 0.2 and front >= back:
        t = "protrusion"
    elif back > 0.2:
        t = "recess"
    elif np.isfinite(med) and abs(med) > offset_m / 2 and spread < offset_m:
        t = "misalignment"
    elif open_loop_m > 0:
        t = "hole"
    else:
        t = "protrusion" if front >= back and front > 0 else ("recess" if back > 0 else "misalignment")
    return DefectEvidence(nv, cov, front, back, med, spread, float(hole_area_m2), float(open_loop_m), t)


@dataclass(frozen=True)
class RepairPlan:
    """What the fusion does in a region: rebuild at all, and which vertices are forced out."""

    rebuild: bool
    forced: np.ndarray  # (nv,) bool
    reason: str
    mesh_only: bool = False  # triangulate the mesh vertices alone (no MLS)


def repair_plan(evidence: DefectEvidence, covered: np.ndarray, offset: np.ndarray, *, typed: bool,
                offset_m: float, conflict: np.ndarray | None = None, uncovered: str = "keep") -> RepairPlan:
    """Typed repair: uncovered regions keep the mesh; covered vertices off the MLS surface by more than
    ``offset_m``, and vertices in conflict with the scan (``conflict``: an MLS point near, none similar),
    are forced out (cut back to the MLS). Untyped (the paper): rebuild, force nothing."""
    nv = len(covered)
    if not typed:
        return RepairPlan(True, np.zeros(nv, bool), "untyped")
    if evidence.type == "uncovered":
        if uncovered == "fill":
            return RepairPlan(True, np.zeros(nv, bool), "no MLS coverage: mesh vertices re-triangulated, holes closed",
                              mesh_only=True)
        return RepairPlan(False, np.zeros(nv, bool), "no MLS coverage: left to the mesh")
    forced = covered & (np.abs(np.nan_to_num(offset)) > offset_m)
    if conflict is not None:
        forced |= conflict
    return RepairPlan(True, forced, f"{evidence.type}: {int(forced.sum())} vertices cut back to the MLS surface")
