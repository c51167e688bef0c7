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
    from tasks.scan.stage import run_scan_file

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    return [run_scan_file(f["path"], f["kind"], f["source"], cfg, wd) for f in files]


@task(name="register", cache_policy=NO_CACHE)
def register_task(records: list[dict], frame_json: dict, cfg_json: dict) -> dict:
    from storage.frame import CampusFrame
    from storage.inputs import InputFile
    from tasks.register.stage import run_register

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
    from tasks.ingest.stage import IngestUnit, run_ingest_unit

    cfg = _cfg(cfg_json)
    wd, frame = WorkDir(cfg.work_dir), CampusFrame.from_json(frame_json)
    m = None if matrix is None else np.asarray(matrix, np.float64)
    return [run_ingest_unit(IngestUnit(**u), cfg, wd, frame, m) for u in units]


@task(name="partition", cache_policy=NO_CACHE)
def partition_task(tile_keys: list[str], cfg_json: dict, frame_json: dict, blocked: dict[str, str]) -> list[dict]:
    """Partition a batch of tiles into patch stores, then label them."""
    from storage.frame import CampusFrame
    from storage.ids import TileId
    from tasks.partition.stage import run_labels_tile, run_partition_tile

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
    from tasks.partition.stage import run_outliers

    cfg = _cfg(cfg_json)
    return run_outliers(cfg, WorkDir(cfg.work_dir))




@task(name="regions", cache_policy=NO_CACHE)
def regions_task(cfg_json: dict) -> dict:
    """Plan the bad regions of the campus (``regions/regions.json``); returns the region keys and a
    weight (estimated working set, bytes) per key for balancing the repair tasks."""
    from tasks.regions.plan import read_plan
    from tasks.repair.stage import run_regions
    from tasks.units import os_error_message

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    try:
        out = run_regions(cfg, wd)
    except (InputError, OSError) as e:
        msg = str(e) if isinstance(e, InputError) else os_error_message(e)
        return {"status": "failed", "error": f"regions: {msg}", "regions": [], "weights": []}
    weight = {r.key: float(max(r.est_bytes, 1)) for r in read_plan(wd.root)}
    return {"status": "done", **out, "weights": [weight.get(k, 1.0) for k in out["regions"]]}


@task(name="repair", cache_policy=NO_CACHE)
def repair_task(region_keys: list[str], cfg_json: dict) -> list[dict]:
    """Repair a batch of regions (fuse -> mesh -> stitch -> texture), one summary each."""
    from tasks.repair.stage import run_region

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    return [run_region(k, cfg, wd) for k in region_keys]


@task(name="merge", cache_policy=NO_CACHE)
def merge_task(tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """Merge a batch of tiles into one clean mesh each (retained faces + rebuilt regions)."""
    from storage.ids import TileId
    from tasks.merge.stage import run_merge_tile

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
    """Repair's rebuilt regions of a tile, in the merge's terms."""
    from tasks.repair.region_io import merge_regions_for_tile

    return merge_regions_for_tile


@task(name="export-nodes", cache_policy=NO_CACHE)
def export_nodes_task(jobs: list) -> list[dict]:
    """Build a batch of 3D Tiles nodes ((index, job) pairs of ``tasks.export.build``); returns their records."""
    from storage.manifest import ManifestRecord, write_record
    from tasks.export.build import build_node
    from tasks.units import peak_rss_mb, reset_peak_rss

    out = []
    for i, job in jobs:
        t0, c0 = time.perf_counter(), time.process_time()
        reset_peak_rss()
        try:
            rec = build_node(job)
        except (InputError, OSError) as e:
            out.append({"index": i, "status": "failed", "error": f"{job.node.key}: {e}"})
            continue
        summary = {"uri": rec.get("uri"), "faces": rec.get("faces"), "peak_rss_mb": peak_rss_mb(),
                   "cpu_seconds": round(time.process_time() - c0, 3)}
        write_record(WorkDir(job.out.parent), ManifestRecord("export", job.node.key, "done", job.fingerprint,
                                                             seconds=time.perf_counter() - t0, summary=summary))
        out.append({"index": i, "record": rec, "status": "done"})
    return out


@task(name="quality", cache_policy=NO_CACHE)
def quality_task(cfg_json: dict, plan: dict, part: tuple[int, int]) -> dict:
    """One share of the model's quality against the truth: {"status", "sums": {model: QualityPartial}}."""
    from tasks.report.stage import run_quality_share

    cfg = _cfg(cfg_json)
    return _recorded("quality", WorkDir(cfg.work_dir), lambda: {"sums": run_quality_share(
        cfg, WorkDir(cfg.work_dir), plan, tuple(part))}, unit=f"share-{part[0]}-of-{part[1]}")


def _recorded(stage: str, wd: WorkDir, fn, unit: str = "campus") -> dict:
    """Run a campus-wide step, record its seconds and peak RSS in the manifest; errors come back as data."""
    from storage.manifest import ManifestRecord, write_record
    from tasks.units import os_error_message, peak_rss_mb, reset_peak_rss

    t0, c0 = time.perf_counter(), time.process_time()
    reset_peak_rss()
    try:
        out = fn()
    except (InputError, OSError) as e:
        msg = str(e) if isinstance(e, InputError) else os_error_message(e)
        return {"status": "failed", "error": f"{stage}: {msg}"}
    summary = {k: v for k, v in out.items() if isinstance(v, (int, float, str, bool)) or v is None}
    summary |= {"peak_rss_mb": peak_rss_mb(), "cpu_seconds": round(time.process_time() - c0, 3)}
    write_record(wd, ManifestRecord(stage, unit, out.get("status", "done"), seconds=time.perf_counter() - t0,
                                    summary=summary))
    return {"status": "done", **out}


@task(name="report", cache_policy=NO_CACHE)
def report_task(cfg_json: dict) -> dict:
    from tasks.report.stage import run_report

    cfg = _cfg(cfg_json)
    return _recorded("report", WorkDir(cfg.work_dir),
                     lambda: run_report(cfg, WorkDir(cfg.work_dir), quality=cfg.report.quality))
