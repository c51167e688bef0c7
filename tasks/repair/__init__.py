"""The repair stage: rebuild each bad region of the plan from the fused mesh and MLS points (paper §5:
graph-cut fusion, Delaunay-based meshing in charts, stitching to the retained mesh, projective texture).

Reads ``regions/regions.json`` (the regions stage), the patch stores of each region's tiles
(``tiles/{ix}_{iy}/points|faces|patches.parquet``), ``campus.json`` (frame, registration) and the vehicle
cameras and images (``repair.texture``). Writes ``regions/{key}/`` (mesh.npz, fused.npz, atlas.jpg,
region.json: :mod:`storage.contracts.region_mesh`) and caches ``regions/_occupancy/{tile}.npz``. A region is
invalidated by a change of its plan entry (patches, bad set, context), of a store of its tiles, of the
cameras file, or of ``repair.*`` / the grid.
"""

from tasks.repair.stage import pending_regions, region_fingerprint, run_region

__all__ = ["pending_regions", "region_fingerprint", "run_region"]
