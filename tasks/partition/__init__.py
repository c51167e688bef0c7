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

from tasks.stages import StageSpec, fixed_tile_batches, lazy_exports

STAGE = StageSpec("partition", "tile", fixed_tile_batches, reads=(
    "manifest.d/partition/", "manifest.d/labels/", "staging/{tile}/", "tiles/{tile}/"))
"""Partition runs the labels of each tile it partitions in the same task (:mod:`tasks.labels`)."""

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.partition.kernels": "build_tile_tables",
    "tasks.partition.stage": "run_partition_tile write_tile_store",
})

__all__ = ["STAGE", "build_tile_tables", "run_partition_tile", "write_tile_store"]
