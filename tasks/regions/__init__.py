"""The regions stage: connected sets of bad patches (26-neighbourhood, across tile borders), the unit of repair.

Reads every live tile's ``patches.parquet`` and its grades under ``repair.grades``
(:func:`storage.patches.state.patch_grades`: ``grades.parquet``, else ``labels.parquet``, or every patch).
Writes ``regions/regions.json`` (:mod:`storage.contracts.region_plan`) and removes the folders and manifest records of
regions the plan no longer names. Invalidated by any change of a tile's store or grades, of
``repair.grades`` / ``repair.regions`` / ``repair.enabled``, or of the grid: it is cheap and re-plans on
every run; each region's repair decides from its own fingerprint whether it must be redone.
"""

from tasks.stages import CAMPUS_WIDE_SKIPS, StageSpec, lazy_exports

STAGE = StageSpec("regions", "campus", skips=CAMPUS_WIDE_SKIPS)

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "storage.contracts.region_plan": "Region read_plan",
    "tasks.regions.plan": "connected_components dilate patch_cost_bytes plan_regions",
    "tasks.regions.stage": "region_weight run_regions run_regions_unit",
})

__all__ = ["STAGE", "Region", "connected_components", "dilate", "patch_cost_bytes", "plan_regions", "read_plan",
           "region_weight", "run_regions", "run_regions_unit"]
