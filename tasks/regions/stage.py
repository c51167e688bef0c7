"""The regions stage on the work dir: read every live tile's patches and grades, plan the regions, write
``regions/regions.json`` and drop what the plan no longer names.

The grades are :func:`storage.patches.state.patch_grades` under ``repair.grades``, the one rule the merge
applies too, so what repair rebuilds and what merge marks bad cannot disagree.
"""

from __future__ import annotations

import shutil
import time

import numpy as np

from storage.contracts.region_plan import REGIONS_DIR, Region, plan_path, read_plan, write_plan
from storage.errors import InputError
from storage.patches.read import PatchTable
from storage.patches.state import GRADE_BAD, patch_grades, store_fingerprint
from storage.workdir.housekeeping import drop_unplanned_records
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.regions.plan import patch_cost_bytes, plan_regions
from tasks.units import Done, record_step, run_unit


def _campus_grades(cfg: CampusConfig, wd: WorkDir) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, dict]:
    """Every live tile's patches: ((n,) int64 sorted keys, (n,) float64 estimated bytes of each, (b,) int64
    bad keys, {tile: grades source}, {tile: store fingerprint})."""
    keys, bad, cost, sources, tile_fp = [], [], [], {}, {}
    for t in wd.live_tiles():
        store = PatchTable(wd.tile_dir(t))  # the patches and side tables: no point or face store is read
        k, g, src = patch_grades(store, cfg.repair.grades)
        p = store.patches()
        keys.append(k)
        bad.append(k[g == GRADE_BAD])
        cost.append(patch_cost_bytes(p["n_points"], p["n_faces"]))
        sources[t.key] = src
        tile_fp[t.key] = store_fingerprint(wd.tile_dir(t))
    all_keys = np.concatenate(keys) if keys else np.zeros(0, np.int64)
    order = np.argsort(all_keys)
    cost_all = np.concatenate(cost)[order] if cost else np.zeros(0)
    bad_keys = np.concatenate(bad) if bad else np.zeros(0, np.int64)
    return all_keys[order], cost_all, bad_keys, sources, tile_fp


def _remove_unplanned(wd: WorkDir, names: set[str]) -> int:
    """Remove the folders and manifest records of regions the plan no longer names; returns folders removed."""
    root = wd.root / REGIONS_DIR
    removed = 0
    for d in root.iterdir() if root.exists() else []:
        if d.is_dir() and d.name not in names and not d.name.startswith("_"):
            shutil.rmtree(d, ignore_errors=True)
            removed += 1
    drop_unplanned_records(wd, "region", names)
    return removed


def region_weight(region: Region) -> float:
    """How heavy a region's repair is, for balancing repair batches: its estimated working set, bytes (>= 1)."""
    return float(max(region.est_bytes, 1))


def run_regions(cfg: CampusConfig, wd: WorkDir) -> dict:
    """Plan the regions over every live tile and write ``regions/regions.json`` (unit: the campus).

    Returns {"status": "done", "regions": [keys], "weights": [estimated working set per key, bytes,
    float >= 1], "n_regions", "n_bad", "n_patches_rebuilt", "split", "removed", "grades": [sources],
    "seconds"}, or {"status": "failed", "error": "regions: <one line>", "regions": [], "weights": []}
    when a store cannot be read or the plan cannot be written.
    """

    def work() -> dict:
        t0 = time.perf_counter()
        rc = cfg.repair.regions
        grid = cfg.grid()
        all_keys, cost_all, bad_keys, sources, tile_fp = _campus_grades(cfg, wd)
        regions = plan_regions(bad_keys, all_keys, grid, min_patches=rc.min_patches, grow_cells=rc.grow_cells,
                               context_cells=rc.context_cells, patch_cost=cost_all,
                               budget_bytes=rc.memory_budget_mb * 2**20) if cfg.repair.enabled else []
        write_plan(wd.root, regions, sources, tile_fp, grid)
        names = {r.key for r in regions}
        return {"regions": [r.key for r in regions], "weights": [region_weight(r) for r in regions],
                "n_regions": len(regions), "n_bad": len(bad_keys),
                "n_patches_rebuilt": int(sum(r.n_patches for r in regions)),
                "split": int(sum(bool(r.parent) for r in regions)), "removed": _remove_unplanned(wd, names),
                "grades": sorted(set(sources.values())), "seconds": time.perf_counter() - t0}

    out = record_step(wd, "regions", "campus", work)
    return out if out["status"] != "failed" else {**out, "regions": [], "weights": []}


def regions_fingerprint(wd: WorkDir) -> str:
    """What the region plan reads: the live tiles' stores with their grades and labels tables."""
    return combine_fingerprints(["regions", *(f"{t.key}:{store_fingerprint(wd.tile_dir(t), ('grades', 'labels'))}"
                                              for t in wd.live_tiles())])


def regions_params(cfg: CampusConfig) -> dict:
    """The region plan's parameters: the repair and partition sections and the grid (more than the plan
    uses: a change reruns the plan, never reuses a stale one)."""
    return {"repair": cfg.repair.model_dump(mode="json"), "partition": cfg.partition.model_dump(mode="json"),
            "grid": cfg.grid().to_json()}


def run_regions_unit(cfg: CampusConfig, wd: WorkDir) -> dict:
    """The region plan as one resumable unit ("regions", "campus"): {"status", "regions": [keys],
    "weights": [bytes per key], ...}; a skipped unit's keys and weights come from the plan on disk."""
    ran: dict = {}

    def work() -> Done:
        ran.update(run_regions(cfg, wd))
        if ran["status"] == "failed":
            raise InputError(None, ran["error"])
        return Done(outputs=[str(plan_path(wd.root).relative_to(wd.root))],
                    summary={k: v for k, v in ran.items() if k not in ("regions", "weights")})

    res = run_unit(wd, "regions", "campus", regions_fingerprint(wd), regions_params(cfg), work)
    if res["status"] == "failed":
        return {**res, "regions": [], "weights": []}
    if ran:
        return {**ran, **res}
    plan = read_plan(wd.root)  # skipped: the plan on disk is current
    return {**res, "regions": [r.key for r in plan], "weights": [region_weight(r) for r in plan]}
