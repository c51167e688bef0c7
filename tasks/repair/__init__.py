"""The repair stage: rebuild each bad region of the plan from the fused mesh and MLS points (paper §5:
graph-cut fusion, Delaunay-based meshing in charts, stitching to the retained mesh, projective texture).

Reads ``regions/regions.json`` (the regions stage), the patch stores of each region's tiles
(``tiles/{ix}_{iy}/points|faces|patches.parquet``; the MLS points without the strips held out for the
quality stage, ``quality.holdout_*``: :mod:`tasks.geometry.holdout`), ``campus.json`` (frame, registration) and the vehicle
cameras and images (``repair.texture``). Writes ``regions/{key}/`` (mesh.npz, fused.npz, atlas.jpg,
region.json: :mod:`storage.contracts.region_mesh`) and caches ``regions/_occupancy/{tile}.npz``. A region is
invalidated by a change of its plan entry (patches, bad set, context), of a store of its tiles, of the
cameras file, or of ``repair.*`` / ``quality.holdout_*`` / the grid.
"""

from tasks.stages import CAMPUS_WIDE_SKIPS, StageSpec, balanced_region_batches, lazy_exports

STAGE = StageSpec("repair", "region", balanced_region_batches, skips=CAMPUS_WIDE_SKIPS)

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {"tasks.repair.stage": "pending_regions region_fingerprint run_region"})

__all__ = ["STAGE", "pending_regions", "region_fingerprint", "run_region"]
