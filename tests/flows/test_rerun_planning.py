"""A rerun maps only the units that must run: the planner decides from one read of the records, and the
summary still counts the skipped ones. Inline (no Prefect), on the hand-made campus with every patch
graded bad, so it has regions to repair."""

from __future__ import annotations

from flows.campus import InlineExecutor, reprocess
from storage.workdir import WorkDir
from tasks.config import CampusConfig


class _Recording(InlineExecutor):
    """The inline executor, noting the units each mapped task was given."""

    def __init__(self):
        self.mapped: dict[str, list] = {}

    def map(self, tsk, batches, label, **consts):
        self.mapped.setdefault(tsk.name, []).extend(u for b in batches for u in b)
        return super().map(tsk, batches, label, **consts)


def test_noop_rerun_maps_no_region_and_counts_them_skipped(handmade_campus):
    cfg = CampusConfig.from_yaml(handmade_campus(), {
        "runner": "inline", "classify.enabled": False, "report.enabled": False, "repair.grades": "all"})
    first = _Recording()
    s1 = reprocess(cfg, first)
    regions = sorted(first.mapped["repair"])
    assert regions and s1["stages"]["repair"]["run"] == len(regions)

    again = _Recording()
    s2 = reprocess(cfg, again)
    assert again.mapped.get("repair", []) == []  # nothing changed: no region is handed to a task
    assert s2["stages"]["repair"] == {"run": 0, "skipped": len(regions), "failed": 0, "units_run": []}

    # a region whose record is gone is redone, and only it
    (WorkDir(cfg.work_dir).manifest_dir / "region" / f"{regions[0]}.json").unlink()
    third = _Recording()
    s3 = reprocess(cfg, third)
    assert third.mapped["repair"] == [regions[0]]
    assert s3["stages"]["repair"]["units_run"] == [regions[0]]
    assert s3["stages"]["repair"]["skipped"] == len(regions) - 1
