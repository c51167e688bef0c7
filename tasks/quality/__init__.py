"""The quality stage: the merged model measured against a synth campus's truth (accuracy, completeness,
F-score, uncovered facade area), and the input mesh beside it when regions were rebuilt.

Reads the merged tiles (``tiles/*/merged.npz`` + ``merged.json``), ``campus.json`` (origin) and the synth
campus's ``truth/truth_mesh*.ply`` (+ its ``mesh/`` input); it runs only where a truth exists. Writes
``report/quality.json``: {"key", "rows": {model name: QualityReport.to_dict()}}. Invalidated by
:func:`quality_key`: any merged tile's content (metadata, size, mtime), the truth mesh, whether a region
was rebuilt, the sample spacing, tile and buffer sizes, and the stage's version.

Accuracy without truth (every campus, ``quality.holdout_share`` > 0): the MLS strips held out of the repair
(:mod:`tasks.geometry.holdout`) measured against the input mesh (the tiles' ``faces.parquet``) and the merged
model, per tile, per building (footprints of the input mesh, :mod:`tasks.geometry.footprints`: raised ground
cells; a point within 1.5 m of one counts as that building) and for the campus. Reads the
tiles' ``points.parquet`` and the merged tiles; writes ``report/holdout.json``; invalidated by the strip
choice, the merged tiles or the point stores (:func:`heldout_key`).

Modules: ``stats`` (mergeable sums, reports), ``metrics`` (one mesh against another), ``tiled`` (tile by
tile, in shares of one model each), ``truth`` (a synth campus's truth, file-level figures), ``stage`` (plan, shares, cache).
"""

from tasks.stages import CAMPUS_WIDE_SKIPS, StageSpec, lazy_exports

STAGE = StageSpec("quality", "share", skips=CAMPUS_WIDE_SKIPS, duration="30s")
HELDOUT_STAGE = StageSpec("holdout", "campus", skips=CAMPUS_WIDE_SKIPS, duration="30s")

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.quality.stage": "ensure_heldout heldout_key heldout_pending read_heldout run_heldout ensure_quality merged_tiles quality_parts quality_plan run_quality_share share_name truth_dir_of write_quality",
})

__all__ = ["HELDOUT_STAGE", "STAGE", "ensure_heldout", "ensure_quality", "heldout_key", "heldout_pending", "read_heldout", "run_heldout", "merged_tiles", "quality_parts", "quality_plan", "run_quality_share", "share_name",
           "truth_dir_of", "write_quality"]
