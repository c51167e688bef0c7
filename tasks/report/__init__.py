"""The report stage: ``output/report.html``, one self-contained page per run (figures embedded as PNG).

Reads ``campus.json``, ``registration.json``, the manifest records, the outlier histograms in ``report/``,
the patch stores (``tiles/*/patches.parquet`` and side tables), the merged tiles, the export's
``output/tileset.json`` + ``tileset.fingerprints.json``, and the quality stage's ``report/quality.json`` and ``report/holdout.json``
(measured here when missing or stale, see ``tasks.quality``). Writes ``output/report.html``,
``report/class_map.png`` and ``report/regions/region_*.png``. Every run rewrites the page; only the region
renders are kept (``report/regions/section.json``), invalidated by the partition, classify and merge records
of the merged tiles and the grid (:func:`region_renders`, which the flow calls beside the export so the
report does not draw them on the critical path).
"""

from tasks.stages import CAMPUS_WIDE_SKIPS, StageSpec, lazy_exports

RENDERS_STAGE = StageSpec("region renders", "campus", skips=CAMPUS_WIDE_SKIPS, duration="15s", priority=-10)
"""The report's figures, drawn beside the export's upper levels (a core idle), behind its nodes."""
STAGE = StageSpec("report", "campus")

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.report.grades": "GradeCensus census_of_stores",
    "tasks.report.stage": "region_renders region_renders_fresh run_region_renders run_report run_report_unit",
})

__all__ = ["RENDERS_STAGE", "STAGE", "GradeCensus", "census_of_stores", "region_renders", "region_renders_fresh", "run_region_renders", "run_report", "run_report_unit"]
