"""Defect-type evidence and the typed repair plan."""

import numpy as np

from tasks.repair.defect_types import classify_evidence, repair_plan


def _ev(offsets, covered=None, **kw):
    off = np.asarray(offsets, float)
    cov = np.ones(len(off), bool) if covered is None else covered
    args = {"offset_m": 0.06, "hole_area_m2": 0.0, "open_loop_m": 0.0, "zone_area_m2": 10.0, "min_coverage": 0.15}
    return classify_evidence(cov, np.where(cov, off, np.nan), **(args | kw))


def test_types_from_offsets():
    flat = np.zeros(100)
    assert _ev(np.r_[np.full(40, 0.3), flat[:60]]).type == "protrusion"
    assert _ev(np.r_[np.full(40, -0.3), flat[:60]]).type == "recess"
    assert _ev(np.r_[np.full(30, 0.2), np.full(30, -0.2), flat[:40]]).type == "misalignment"  # a warp: both sides
    assert _ev(np.full(100, 0.04)).type == "misalignment"  # a shift
    assert _ev(flat, hole_area_m2=3.0).type == "hole"
    assert _ev(flat, covered=np.arange(100) < 10).type == "uncovered"


def test_typed_plan_cuts_back_or_keeps():
    off = np.r_[np.full(40, 0.3), np.zeros(60)]
    ev = _ev(off)
    plan = repair_plan(ev, np.ones(100, bool), off, typed=True, offset_m=0.06)
    assert plan.rebuild and plan.forced.sum() == 40
    assert not repair_plan(ev, np.ones(100, bool), off, typed=False, offset_m=0.06).forced.any()
    unc = _ev(np.zeros(100), covered=np.zeros(100, bool))
    assert not repair_plan(unc, np.zeros(100, bool), np.full(100, np.nan), typed=True, offset_m=0.06).rebuild
    fill = repair_plan(unc, np.zeros(100, bool), np.full(100, np.nan), typed=True, offset_m=0.06, uncovered="fill")
    assert fill.rebuild and fill.mesh_only
