"""The regions stage: connected sets of bad patches (26-neighbourhood, across tile borders), the unit of repair.

Reads every live tile's ``patches.parquet`` and its grades under ``repair.grades``
(:func:`storage.patches.state.patch_grades`: ``grades.parquet``, else ``labels.parquet``, or every patch).
Writes ``regions/regions.json`` (:mod:`storage.contracts.region_plan`) and removes the folders and manifest records of
regions the plan no longer names. Invalidated by any change of a tile's store or grades, of
``repair.grades`` / ``repair.regions`` / ``repair.enabled``, or of the grid: it is cheap and re-plans on
every run; each region's repair decides from its own fingerprint whether it must be redone.
"""

from storage.contracts.region_plan import Region, read_plan
from tasks.regions.plan import connected_components, dilate, patch_cost_bytes, plan_regions
from tasks.regions.stage import region_weight, run_regions

__all__ = ["Region", "connected_components", "dilate", "patch_cost_bytes", "plan_regions", "read_plan",
           "region_weight", "run_regions"]
