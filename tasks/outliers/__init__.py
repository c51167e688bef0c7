"""The outliers stage (Liu et al. 2023, §3.2.2): patches with implausibly few or many points or faces.

- Reads: ``patches.parquet`` of every live tile (done, not stale) and each tile's ``outliers.parquet``.
- Writes: ``tiles/{tile}/outliers.parquet`` (patch, outlier_points, outlier_faces, outlier) only where a
  tile's flags change, ``report/patch_{points,faces}_histogram.png``, and one manifest record (``campus``).
- Invalidated by: nothing is skipped; it reruns on every run (a campus-wide fit: any tile's counts move
  every threshold), but rewrites only the tiles whose flags changed.
"""

from tasks.outliers.fit import OutlierFit, fit_count_outliers
from tasks.outliers.stage import run_outliers

__all__ = ["OutlierFit", "fit_count_outliers", "run_outliers"]
