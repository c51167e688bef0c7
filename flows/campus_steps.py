"""The campus-wide steps of the flow (patch outliers, region plan, run report) as resumable units: each
gets an input fingerprint and a parameter dict, so ``tasks.units.run_unit`` skips it when nothing it
reads changed, and the flow's planner (``flows.planned``) launches no task run for it on a no-op rerun.

What each step reads, i.e. what enters its fingerprint:

- outliers: the patch tables of every live tile (store files' sizes and mtimes, not the side tables it
  writes itself) and the ``partition`` outlier / minimum-count fields;
- regions: the live tiles' stores with their grades and labels tables, and the ``repair`` and
  ``partition`` config sections (more than the plan uses: a change reruns the plan, never reuses a stale one);
- report: every manifest record but the report's own (status, fingerprint, parameters and, for the units
  skipped by fingerprint, seconds: a unit that ran this run changes it), the content of ``tileset.json`` and
  ``report/quality.json``, the ``report`` and ``partition`` config sections and ``classify.threshold`` (a
  new network changes the classify records).
"""

from __future__ import annotations

import json

from storage.atomic import file_sha256
from storage.patches.state import store_fingerprint
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import all_records, combine_fingerprints

__all__ = ["outliers_fingerprint", "outliers_outputs", "regions_fingerprint", "regions_params",
           "report_fingerprint", "report_params"]

# steps recorded by record_step on every run they make: their seconds change on each run
_ALWAYS_RECORDED = ("export", "quality", "outliers", "regions")


def _live_stores(wd: WorkDir, sides: tuple[str, ...] = ()) -> list[str]:
    return [f"{t.key}:{store_fingerprint(wd.tile_dir(t), sides)}" for t in wd.live_tiles()]


def outliers_fingerprint(wd: WorkDir) -> str:
    """What the outlier fit reads: every live tile's store (sizes and mtimes)."""
    return combine_fingerprints(["outliers", *_live_stores(wd)])


def outliers_outputs(wd: WorkDir) -> list[str]:
    """The outlier fit's files (work-dir relative) that exist: each live tile's ``outliers`` side table and
    the two histograms."""
    from storage.patches.schema import side_table_path

    paths = [side_table_path(wd.tile_dir(t), "outliers") for t in wd.live_tiles()]
    paths += [wd.report_dir / f"patch_{n}_histogram.png" for n in ("points", "faces")]
    return [str(p.relative_to(wd.root)) for p in paths if p.exists()]


def regions_fingerprint(wd: WorkDir) -> str:
    """What the region plan reads: the live tiles' stores with their grades and labels tables."""
    return combine_fingerprints(["regions", *_live_stores(wd, ("grades", "labels"))])


def regions_params(cfg) -> dict:
    """The region plan's parameters (cfg: CampusConfig): the repair and partition sections and the grid."""
    return {"repair": cfg.repair.model_dump(mode="json"), "partition": cfg.partition.model_dump(mode="json"),
            "grid": cfg.grid().to_json()}


def _sha(path) -> str:
    try:
        return file_sha256(path)
    except OSError:
        return "-"


def report_fingerprint(wd: WorkDir) -> str:
    """What the run report shows: the manifest records, the tileset and the quality figures."""
    parts = []
    for r in all_records(wd):
        if r.stage == "report":
            continue
        secs = None if r.stage in _ALWAYS_RECORDED else r.seconds
        parts.append(json.dumps([r.stage, r.unit, r.status, r.fingerprint, r.params_hash, secs, r.error]))
    parts += [_sha(wd.root / "output" / "tileset.json"), _sha(wd.report_dir / "quality.json")]
    return combine_fingerprints(sorted(parts))


REPORT_VERSION = 1  # bumped whenever report.html changes for the same inputs


def report_params(cfg) -> dict:
    """The run report's parameters (cfg: CampusConfig), with the package and report versions: an upgrade
    that changes the page (bump :data:`REPORT_VERSION`) redraws it."""
    from storage import __version__

    return {"code_version": __version__, "report_version": REPORT_VERSION, "report": cfg.report.model_dump(mode="json"),
            "classify_threshold": cfg.classify.threshold,
            "partition": cfg.partition.model_dump(mode="json"), "grid": cfg.grid().to_json()}
