"""The outliers stage (Liu et al. 2023, §3.2.2): patches with implausibly few or many points or faces.

- Reads: ``patches.parquet`` of every live tile (done, not stale) and each tile's ``outliers.parquet``.
- Writes: ``tiles/{tile}/outliers.parquet`` (patch, outlier_points, outlier_faces, outlier) only where a
  tile's flags change, ``report/patch_{points,faces}_histogram.png``, and one manifest record (``campus``).
- Invalidated by: nothing is skipped; it reruns on every run (a campus-wide fit: any tile's counts move
  every threshold), but rewrites only the tiles whose flags changed.
"""

from tasks.stages import CAMPUS_WIDE_SKIPS, StageSpec, lazy_exports

STAGE = StageSpec("outliers", "campus", skips=CAMPUS_WIDE_SKIPS)

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.outliers.fit": "OutlierFit fit_count_outliers",
    "tasks.outliers.stage": "run_outliers run_outliers_unit",
})

__all__ = ["STAGE", "OutlierFit", "fit_count_outliers", "run_outliers", "run_outliers_unit"]
