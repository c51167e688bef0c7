"""The Prefect tasks of the campus flow: thin wrappers that take ids, paths, small JSON records and the
config, call a stage function of ``tasks/`` and return its small summaries (never arrays).

Expected failures come back as failed unit summaries; anything else raises (a bug), and Prefect keeps
its traceback in the run history.
"""

from __future__ import annotations

import os
import time

from prefect import task
from prefect.cache_policies import NONE as NO_CACHE

from storage.errors import InputError
from storage.workdir import WorkDir
from tasks.config import CampusConfig

def _cfg(cfg_json: dict) -> CampusConfig:
    return CampusConfig.model_validate(cfg_json)


@task(name="scan", cache_policy=NO_CACHE)
def scan_task(files: list[dict], cfg_json: dict) -> list[dict]:
    """Scan a batch of input files ({"path", "kind", "source"})."""
    from tasks.scan import run_scan_file

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    return [run_scan_file(f["path"], f["kind"], f["source"], cfg, wd) for f in files]


@task(name="register", cache_policy=NO_CACHE)
def register_task(records: list[dict], frame_json: dict, cfg_json: dict) -> dict:
    from storage.frame import CampusFrame
    from storage.inputs import InputFile
    from tasks.register_stage import run_register

    cfg = _cfg(cfg_json)
    try:
        return run_register([InputFile(**r) for r in records], CampusFrame.from_json(frame_json), cfg,
                            WorkDir(cfg.work_dir))
    except InputError as e:
        return {"error": str(e)}


@task(name="ingest", cache_policy=NO_CACHE)
def ingest_task(units: list[dict], cfg_json: dict, frame_json: dict, matrix: list | None) -> list[dict]:
    """Route a batch of ingest units to staging files."""
    import numpy as np

    from storage.frame import CampusFrame
    from tasks.ingest import IngestUnit, run_ingest_unit

    cfg = _cfg(cfg_json)
    wd, frame = WorkDir(cfg.work_dir), CampusFrame.from_json(frame_json)
    m = None if matrix is None else np.asarray(matrix, np.float64)
    return [run_ingest_unit(IngestUnit(**u), cfg, wd, frame, m) for u in units]


@task(name="partition", cache_policy=NO_CACHE)
def partition_task(tile_keys: list[str], cfg_json: dict, frame_json: dict, blocked: dict[str, str]) -> list[dict]:
    """Partition a batch of tiles into patch stores, then label them."""
    from storage.frame import CampusFrame
    from storage.ids import TileId
    from tasks.patches import run_labels_tile, run_partition_tile

    delay = float(os.environ.get("MS3D_FAULT_PARTITION_DELAY_S", "0") or 0)  # fault-injection hook for tests
    cfg = _cfg(cfg_json)
    wd, frame = WorkDir(cfg.work_dir), CampusFrame.from_json(frame_json)
    out = []
    for k in tile_keys:
        if delay:
            time.sleep(delay)
        t = TileId.from_key(k)
        res = run_partition_tile(t, cfg, wd, frame, blocked.get(k))
        if res["status"] == "done":
            lab = run_labels_tile(t, cfg, wd)
            if lab is not None and lab["status"] == "failed":
                res = {**res, "labels_error": lab["error"]}
        out.append(res)
    return out


@task(name="outliers", cache_policy=NO_CACHE)
def outliers_task(cfg_json: dict) -> dict:
    from tasks.patches import run_outliers

    cfg = _cfg(cfg_json)
    return run_outliers(cfg, WorkDir(cfg.work_dir))




@task(name="merge", cache_policy=NO_CACHE)
def merge_task(tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """Merge a batch of tiles into one clean mesh each (retained faces + rebuilt regions)."""
    from storage.ids import TileId
    from tasks.merge import run_merge_tile

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    regions = _region_source()
    out = []
    for k in tile_keys:
        res = run_merge_tile(TileId.from_key(k), cfg, wd, regions)
        if res is not None:
            out.append(res)
    return out


def _region_source():
    """Repair's ``region_meshes_for_tile`` once the repair stage exists, else None (retained mesh alone)."""
    try:
        from tasks.repair import region_meshes_for_tile
    except ImportError:
        return None
    return region_meshes_for_tile


@task(name="export", cache_policy=NO_CACHE)
def export_task(cfg_json: dict) -> dict:
    """3D Tiles of the merged tiles (only the tiles and ancestors whose content changed are rewritten)."""
    from tasks.export_stage import run_export_stage

    cfg = _cfg(cfg_json)
    return run_export_stage(cfg, WorkDir(cfg.work_dir))


@task(name="report", cache_policy=NO_CACHE)
def report_task(cfg_json: dict) -> dict:
    from tasks.report import run_report
    from tasks.units import peak_rss_mb, reset_peak_rss

    cfg = _cfg(cfg_json)
    reset_peak_rss()
    try:
        out = run_report(cfg, WorkDir(cfg.work_dir), quality=cfg.report.quality)
    except (InputError, OSError) as e:
        return {"status": "failed", "error": f"report: {e}"}
    return out | {"status": "done", "peak_rss_mb": peak_rss_mb()}
