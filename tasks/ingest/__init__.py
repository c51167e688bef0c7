"""The ingest stage: convert the inputs to the campus frame and route points and faces to their tiles.

- Reads: the input files (a mesh whole, a cloud by ranges of ``tiling.chunk_points`` points), the campus
  frame and, for point units, the registration matrix.
- Writes: sorted staging runs ``staging/{tile}/{unit key}-{part:03d}.arrow`` (contract:
  :mod:`storage.contracts.staging`) and one manifest record per unit.
- Invalidated by: the unit's key (source id, content fingerprint, range), its point range, the campus
  frame, the registration (point units only), the ingest parameters and ``STAGE_VERSIONS["ingest"]``.

The plan (:mod:`tasks.ingest.plan`) names the units, batches them, and says which tiles a bad input
blocks; :func:`storage.contracts.staging.prune_staging` then removes what the plan no longer names, so a tile is
rebuilt exactly when the set of files that feed it changes.
"""

from tasks.ingest.plan import IngestUnit, blocked_tiles, ingest_batches, input_tiles, plan_units, tiles_hint
from tasks.ingest.stage import run_ingest_unit

__all__ = ["IngestUnit", "blocked_tiles", "ingest_batches", "input_tiles", "plan_units", "run_ingest_unit",
           "tiles_hint"]
