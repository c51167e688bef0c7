"""The classify stage: grade every (mesh patch, point patch) pair of a tile good or bad with MS3DQE-Net.

Reads a tile's store (``tiles/{ix}_{iy}/points|faces|patches.parquet``) and the model checkpoint
(``classify.model``, else the shipped ``ms3d_model/weights/default.pt``) and the user's labels
(``labels/*.csv``, which win for the patches they name). Writes
``tiles/{ix}_{iy}/grades.parquet`` (score, grade per patch; -1 for patches that are not pairs, unless the
geometric evidence of ``classify.evidence`` (:mod:`tasks.classify.evidence`) grades them bad). Invalidated
by a re-partitioned tile (:func:`storage.patches.state.store_fingerprint`), a new model (its sha256) or a new
threshold / ``partition.min_faces`` / ``min_points`` / ``classify.evidence*``, or new user labels in the
tile; with ``classify.enabled`` off the grades are removed.
Also the pair readers training and evaluation use (:func:`read_tile_pairs`, :func:`campus_pair_set`).
"""

from tasks.stages import StageSpec, largest_first_tile_batches, lazy_exports

STAGE = StageSpec("classify", "tile", largest_first_tile_batches, reads=("manifest.d/classify/", "tiles/{tile}/"))
"""A pair's neighbourhood cues stay within its tile; the largest stores start first."""

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.classify.pairs": "CACHE_VERSION featurise_tile_pairs read_tile_pairs",
    "tasks.classify.stage": "DEFAULT_MODEL DEFAULT_MODEL_TRAINING_SEEDS campus_pair_set grade_pairs grading_threshold load_model run_classify_tile",
})

__all__ = ["STAGE", "CACHE_VERSION", "DEFAULT_MODEL", "DEFAULT_MODEL_TRAINING_SEEDS", "campus_pair_set", "featurise_tile_pairs", "grade_pairs", "grading_threshold", "load_model",
           "read_tile_pairs", "run_classify_tile"]
