"""The partition stage: each tile's staging runs -> its Parquet patch store (Liu et al. 2023, §3.2.1,
Algorithms 1 and 2 on a world-anchored patch grid).

- Reads: the tile's staging runs ``staging/{tile}/*.arrow`` (:mod:`storage.contracts.staging`).
- Writes: ``tiles/{tile}/points.parquet``, ``faces.parquet``, ``patches.parquet`` (sorted by patch; the runs
  merged in the order of their content digests, :func:`storage.contracts.columns.content_digest`, so renamed or
  re-uploaded inputs give the same store), removes the tile's side tables (they describe the old patches),
  ``stale.json`` on a blocked tile, and one manifest record per tile.
- Invalidated by: the names and content fingerprints of the tile's staging runs, the blocking error of a
  bad input, the campus frame, the partition parameters and ``STAGE_VERSIONS["partition"]``.

Pure kernels: :mod:`tasks.partition.kernels` (in memory), :mod:`tasks.partition.stream` (bounded memory,
same files).
"""

from tasks.partition.kernels import build_tile_tables
from tasks.partition.stage import run_partition_tile, write_tile_store

__all__ = ["build_tile_tables", "run_partition_tile", "write_tile_store"]
