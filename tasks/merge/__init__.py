"""The merge stage: per tile, the retained mesh and the rebuilt regions become one welded mesh.

Reads a tile's store (``faces.parquet``, ``patches.parquet``, ``points.parquet`` for the faces' scan-to-model
distance, ``grades.parquet``'s scores), its grades under ``repair.grades``
(``grades.parquet`` / ``labels.parquet``, or every patch bad: :func:`storage.patches.state.patch_grades`, the
regions stage's rule), ``campus.json`` (frame) and the rebuilt regions reaching into it (``regions/``:
:mod:`storage.contracts.region_mesh`). Writes ``tiles/{ix}_{iy}/merged.npz`` + ``merged.json``
(:mod:`storage.contracts.tile_mesh`). Invalidated by a change of the store (points too), of ``grades.parquet``, of the grade table it reads (or of
``repair.grades`` to one that reads another), of the frame, of a rebuilt region touching the tile, or of
the grid.
"""

from tasks.stages import StageSpec, fixed_tile_batches, lazy_exports

STAGE = StageSpec("merge", "tile", fixed_tile_batches, reads=(
    "manifest.d/merge/", "campus.json", "regions/", "tiles/{tile}/"))

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "storage.contracts.region_mesh": "RegionMesh",
    "tasks.merge.before": "input_tile_mesh",
    "tasks.merge.soup": "FaceSoup weld_soup",
    "tasks.merge.stage": "run_merge_tile",
    "tasks.merge.tile": "MergeStats faces_in_tile merge_tile retained_soup",
})

__all__ = ["STAGE", "FaceSoup", "MergeStats", "RegionMesh", "faces_in_tile", "input_tile_mesh", "merge_tile",
           "retained_soup",
           "run_merge_tile", "weld_soup"]
