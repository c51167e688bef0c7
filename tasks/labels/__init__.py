"""The labels stage: ground-truth grades of each tile's patches, when ``inputs.labels`` is configured.

- Reads: the labels file (a synth ``defects.json`` or a CSV of world-anchored patch ids) and the tile's
  ``patches.parquet``.
- Writes: ``tiles/{tile}/labels.parquet`` (patch, label: 1 bad, 0 good) and one manifest record per tile;
  without a labels file, removes a stale labels table.
- Invalidated by: the labels file's content and path, the tile's patch store (its modification time:
  a re-partitioned tile is relabelled), the labels parameters and ``STAGE_VERSIONS["labels"]``.
"""

from tasks.stages import lazy_exports

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {"tasks.labels.stage": "bad_patch_keys run_labels_tile"})

__all__ = ["bad_patch_keys", "run_labels_tile"]
