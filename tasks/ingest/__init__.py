"""The ingest stage: convert the inputs to the campus frame and route points and faces to their tiles.

- Reads: the input files (a mesh whole, a cloud by ranges of ``tiling.chunk_points`` points, only those in
  ``inputs.points_bounds``: a COPC cloud by its octree nodes over that box), the campus frame and, for point
  units, the registration matrix.
- Writes: sorted staging runs ``staging/{tile}/{unit key}-{part:03d}.arrow`` (contract:
  :mod:`storage.contracts.staging`) and one manifest record per unit.
- Invalidated by: the unit's key (source id, content fingerprint, range), its point range, the campus
  frame, the registration and the points box (point units only), the ingest parameters and
  ``STAGE_VERSIONS["ingest"]``.

The plan (:mod:`tasks.ingest.plan`) names the units, batches them, and says which tiles a bad input
blocks; :func:`storage.contracts.staging.prune_staging` then removes what the plan no longer names, so a tile is
rebuilt exactly when the set of files that feed it changes.
"""

from tasks.stages import BatchContext, StageSpec, lazy_exports


def ingest_task_batches(units: list[dict], ctx: BatchContext) -> list[list[dict]]:
    """The ingest stage's batching rule over unit JSON: the meshes' batches of
    :func:`tasks.ingest.plan.ingest_batches`, then one point range per batch."""
    from tasks.ingest.plan import IngestUnit, ingest_batches  # on first use (lazy_exports)

    meshes, points = ingest_batches([IngestUnit(**u) for u in units], ctx.n_workers)
    return meshes + points

STAGE = StageSpec("ingest", "ingest unit", ingest_task_batches, reads=("manifest.d/ingest/",))
"""A redone unit removes its earlier runs by their records (:mod:`storage.recorded`): on a bucket it downloads none."""

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.ingest.plan": "IngestUnit blocked_tiles ingest_batches ingest_task_batches input_tiles plan_units tiles_hint",
    "tasks.ingest.stage": "run_ingest_unit",
})

__all__ = ["STAGE", "IngestUnit", "blocked_tiles", "ingest_batches", "input_tiles", "plan_units", "run_ingest_unit",
           "tiles_hint"]
