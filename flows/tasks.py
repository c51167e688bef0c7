"""Every Prefect task of the campus flow: a thin wrapper that takes ids, paths, small JSON records and the
config, calls one stage entry point of ``tasks/`` and returns its small summaries (never arrays).

Expected failures come back as failed unit summaries (``tasks.units``); anything else raises (a bug), and
Prefect keeps its traceback in the run history. Heavy objects (the network) are loaded once per worker
process by the stages themselves.
"""

from __future__ import annotations

import os
import time
from functools import partial

import numpy as np
from prefect import task
from prefect.cache_policies import NONE as NO_CACHE

from flows.remote import local_truth_plan, local_view, synced, work_dir_of
from storage.errors import InputError
from storage.frame import CampusFrame
from storage.ids import TileId
from storage.inputs.identity import InputFile
from storage.workdir.layout import WorkDir
from tasks.config import CampusConfig
from tasks.units import Done, MustRun, is_planning, record_step, run_unit, skipped_summary


def config_of(cfg_json: dict) -> tuple[CampusConfig, WorkDir]:
    """The validated config of a task's JSON argument and its work dir."""
    cfg = CampusConfig.model_validate(cfg_json)
    return cfg, work_dir_of(cfg)  # a work dir by URL: this process's mirror (flows.remote)


@task(name="scan", cache_policy=NO_CACHE)
@synced
def scan_task(files: list[dict], cfg_json: dict) -> list[dict]:
    """Scan a batch of input files ({"path", "kind", "source"}), one summary each."""
    from tasks.scan import run_scan_file

    cfg, wd = config_of(cfg_json)
    return [run_scan_file(f["path"], f["kind"], f["source"], cfg, wd) for f in files]


@task(name="register", cache_policy=NO_CACHE)
@synced
def register_task(records: list[dict], frame_json: dict, cfg_json: dict) -> dict:
    """The campus registration ({"matrix", "scale", ...}), or {"error": one line}."""
    from tasks.register import run_register

    cfg, wd = config_of(cfg_json)
    try:
        return run_register([InputFile(**r) for r in records], CampusFrame.from_json(frame_json), cfg, wd)
    except InputError as e:
        return {"error": str(e)}


@task(name="ingest", cache_policy=NO_CACHE)
@synced
def ingest_task(units: list[dict], cfg_json: dict, frame_json: dict, matrix: list | None) -> list[dict]:
    """Route a batch of ingest units to staging files; matrix: the (4, 4) registration (None for meshes)."""
    from tasks.ingest import IngestUnit, run_ingest_unit

    cfg, wd = config_of(cfg_json)
    frame = CampusFrame.from_json(frame_json)
    m = None if matrix is None else np.asarray(matrix, np.float64)
    return [run_ingest_unit(IngestUnit(**u), cfg, wd, frame, m) for u in units]


@task(name="partition", cache_policy=NO_CACHE)
@synced
def partition_task(tile_keys: list[str], cfg_json: dict, frame_json: dict, blocked: dict[str, str]) -> list[dict]:
    """Partition a batch of tiles into patch stores, then label each one partitioned (a labels failure
    comes back as the tile's ``labels_error``)."""
    from tasks.labels import run_labels_tile
    from tasks.partition import run_partition_tile

    delay = float(os.environ.get("MS3D_FAULT_PARTITION_DELAY_S", "0") or 0)  # fault-injection hook for tests
    cfg, wd = config_of(cfg_json)
    frame = CampusFrame.from_json(frame_json)
    out = []
    for k in tile_keys:
        if delay and not is_planning():
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
@synced
def outliers_task(cfg_json: dict) -> dict:
    """The campus-wide patch outlier fit; skipped while no live store changed (``flows.campus_steps``)."""
    import json

    from flows.campus_steps import outliers_fingerprint, outliers_outputs
    from tasks.outliers import run_outliers

    cfg, wd = config_of(cfg_json)

    def work() -> Done:
        out = json.loads(json.dumps(run_outliers(cfg, wd)))
        return Done(outputs=outliers_outputs(wd), summary=out)

    return run_unit(wd, "outliers", "campus", outliers_fingerprint(wd), cfg.stage_params("outliers"), work)


def _per_tile(run, tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """``run(tile, cfg, wd)`` over a batch of tiles; the summaries of the tiles that had work (not None)."""
    cfg, wd = config_of(cfg_json)
    return [res for k in tile_keys if (res := run(TileId.from_key(k), cfg, wd)) is not None]


@task(name="classify", cache_policy=NO_CACHE)
@synced
def classify_task(tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """Grade the pairs of a batch of tiles (MS3DQE-Net); one summary per tile that has a live store."""
    from tasks.classify import run_classify_tile

    return _per_tile(run_classify_tile, tile_keys, cfg_json)


@task(name="regions", cache_policy=NO_CACHE)
@synced
def regions_task(cfg_json: dict) -> dict:
    """Plan the bad regions of the campus: {"status", "regions": [keys], "weights": [bytes per key], ...}."""
    from flows.campus_steps import regions_fingerprint, regions_params
    from storage.contracts.region_plan import plan_path, read_plan
    from tasks.regions import region_weight, run_regions

    cfg, wd = config_of(cfg_json)
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


@task(name="repair", cache_policy=NO_CACHE)
@synced
def repair_task(region_keys: list[str], cfg_json: dict) -> list[dict]:
    """Repair a batch of regions (fuse -> mesh -> stitch -> texture), one summary each."""
    from storage.contracts.region_plan import read_plan
    from tasks.repair import run_region

    cfg, wd = config_of(cfg_json)
    cfg = local_view(cfg, "texture")  # cameras and images by URL: this worker's staged copies
    plan = {r.key: r for r in read_plan(wd.root)}  # once per batch, not once per region
    return [run_region(k, cfg, wd, plan) for k in region_keys]


@task(name="merge", cache_policy=NO_CACHE)
@synced
def merge_task(tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """Merge a batch of tiles into one clean mesh each (retained faces + rebuilt regions)."""
    from tasks.merge import run_merge_tile

    return _per_tile(run_merge_tile, tile_keys, cfg_json)


@task(name="export-nodes", cache_policy=NO_CACHE)
@synced
def export_nodes_task(jobs: list) -> list[dict]:
    """Build a batch of 3D Tiles nodes ((index, job) pairs); one {"index", "status", "record" | "error"} each."""
    from tasks.export import build_nodes

    return build_nodes(jobs)


@task(name="quality", cache_policy=NO_CACHE)
@synced
def quality_task(cfg_json: dict, plan: dict, part: tuple) -> dict:
    """One share of the model's quality against the truth: {"status", "sums": {model: partial sums}}."""
    from tasks.quality import run_quality_share, share_name

    cfg, wd = config_of(cfg_json)
    plan = local_truth_plan(cfg, plan)  # a truth by URL: this worker's staged copy
    return record_step(wd, "quality", share_name(part),
                       lambda: {"sums": run_quality_share(cfg, wd, plan, tuple(part))})


@task(name="region renders", cache_policy=NO_CACHE)
@synced
def region_renders_task(cfg_json: dict) -> dict:
    """Draw the rebuilt regions' before/after renders for the report (``report/regions/``, kept under a key of
    their inputs), beside the export: {"status", "figures" | "error"}. A failure costs nothing but time: the
    report draws them itself and says why not."""
    from tasks.report import region_renders

    if is_planning():
        return {"status": "skipped"}
    cfg, wd = config_of(cfg_json)
    try:
        sec, _ = region_renders(cfg, wd)
    except (InputError, OSError, ValueError, KeyError) as e:
        return {"status": "failed", "error": str(e).splitlines()[0] if str(e) else type(e).__name__}
    return {"status": "done", "figures": len(sec.figures)}


@task(name="report", cache_policy=NO_CACHE)
@synced
def report_task(cfg_json: dict) -> dict:
    """Write the run report (``output/report.html``)."""
    from flows.campus_steps import report_fingerprint, report_params
    from storage.workdir.manifest import is_done, params_hash
    from tasks.report import run_report

    cfg, wd = config_of(cfg_json)
    fp, ph = report_fingerprint(wd), params_hash(report_params(cfg))
    rec = is_done(wd, "report", "campus", fp, ph)
    if rec is not None and (wd.root / "output" / "report.html").exists():
        return {**skipped_summary(rec), "report": str(wd.root / "output" / "report.html")}
    if is_planning():
        raise MustRun("report", "campus")
    return record_step(wd, "report", "campus", partial(run_report, cfg, wd, quality=cfg.report.quality), fp, ph)
