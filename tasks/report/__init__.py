"""The report stage: ``output/report.html``, one self-contained page per run (figures embedded as PNG).

Reads ``campus.json``, ``registration.json``, the manifest records, the outlier histograms in ``report/``,
the patch stores (``tiles/*/patches.parquet`` and side tables), the merged tiles, the export's
``output/tileset.json`` + ``tileset.fingerprints.json``, and the quality stage's ``report/quality.json``
(measured here when missing or stale, see ``tasks.quality``). Writes ``output/report.html``,
``report/class_map.png`` and ``report/regions/region_*.png``. Every run rewrites the page; only the region
renders are kept (``report/regions/section.json``), invalidated by the partition, classify and merge records
of the merged tiles and the grid (:func:`region_renders`, which the flow calls beside the export so the
report does not draw them on the critical path).
"""

from tasks.report.grades import GradeCensus, census_of_stores
from tasks.report.stage import region_renders, region_renders_fresh, run_report

__all__ = ["GradeCensus", "census_of_stores", "region_renders", "region_renders_fresh", "run_report"]
