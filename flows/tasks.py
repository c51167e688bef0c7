"""Every Prefect task of the campus flow: a thin wrapper that takes ids, paths, small JSON records and the
config, calls one stage entry point of ``tasks/`` and returns its small summaries (never arrays).

Expected failures come back as failed unit summaries (``tasks.units``); anything else raises (a bug), and
Prefect keeps its traceback in the run history. Heavy objects (the network) are loaded once per worker
process by the stages themselves.
"""

from __future__ import annotations

import os
import time

import numpy as np
from prefect import task
from prefect.cache_policies import NONE as NO_CACHE

from flows.remote import is_remote, local_truth_plan, local_view, mirror_for, synced, work_dir_of
from storage.errors import InputError
from storage.frame import CampusFrame
from storage.ids import TileId
from storage.inputs.identity import InputFile
from storage.workdir.layout import WorkDir
from tasks.classify import STAGE as CLASSIFY
from tasks.config import CampusConfig
from tasks.export import STAGE as EXPORT
from tasks.ingest import STAGE as INGEST
from tasks.merge import STAGE as MERGE
from tasks.outliers import STAGE as OUTLIERS
from tasks.partition import STAGE as PARTITION
from tasks.quality import HELDOUT_STAGE
from tasks.quality import STAGE as QUALITY
from tasks.regions import STAGE as REGIONS
from tasks.register import STAGE as REGISTER
from tasks.repair import STAGE as REPAIR
from tasks.report import RENDERS_STAGE
from tasks.report import STAGE as REPORT
from tasks.scan import STAGE as SCAN
from tasks.stages import StageSpec
from tasks.units import is_planning, record_step


def stage_task(spec: StageSpec):
    """The Prefect task of a stage's declaration (``tasks.stages.StageSpec``): named by the stage, no Prefect
    cache (the manifest decides what is done), synced with a work dir by URL as the declaration says; the
    declaration stays on the task (``.spec``) for the flow's batching, priorities and durations."""
    def wrap(fn):
        tsk = task(name=spec.name, cache_policy=NO_CACHE)(synced(spec)(fn))
        tsk.spec = spec
        return tsk
    return wrap


def config_of(cfg_json: dict) -> tuple[CampusConfig, WorkDir]:
    """The validated config of a task's JSON argument and its work dir."""
    cfg = CampusConfig.model_validate(cfg_json)
    return cfg, work_dir_of(cfg)  # a work dir by URL: this process's mirror (flows.remote)


@stage_task(SCAN)
def scan_task(files: list[dict], cfg_json: dict) -> list[dict]:
    """Scan a batch of input files ({"path", "kind", "source"}), one summary each."""
    from tasks.scan import run_scan_file

    cfg, wd = config_of(cfg_json)
    return [run_scan_file(f["path"], f["kind"], f["source"], cfg, wd) for f in files]


@stage_task(REGISTER)
def register_task(records: list[dict], frame_json: dict, cfg_json: dict) -> dict:
    """The campus registration ({"matrix", "scale", ...}), or {"error": one line}."""
    from tasks.register import run_register

    cfg, wd = config_of(cfg_json)
    try:
        return run_register([InputFile(**r) for r in records], CampusFrame.from_json(frame_json), cfg, wd)
    except InputError as e:
        return {"error": str(e)}


@stage_task(INGEST)
def ingest_task(units: list[dict], cfg_json: dict, frame_json: dict, matrix: list | None) -> list[dict]:
    """Route a batch of ingest units to staging files; matrix: the (4, 4) registration (None for meshes)."""
    from tasks.ingest import IngestUnit, run_ingest_unit

    cfg, wd = config_of(cfg_json)
    frame = CampusFrame.from_json(frame_json)
    m = None if matrix is None else np.asarray(matrix, np.float64)
    return [run_ingest_unit(IngestUnit(**u), cfg, wd, frame, m) for u in units]


@stage_task(PARTITION)
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


@stage_task(OUTLIERS)
def outliers_task(cfg_json: dict) -> dict:
    """The campus-wide patch outlier fit; skipped while no live store changed."""
    from tasks.outliers import run_outliers_unit

    return run_outliers_unit(*config_of(cfg_json))


def _per_tile(run, tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """``run(tile, cfg, wd)`` over a batch of tiles; the summaries of the tiles that had work (not None)."""
    cfg, wd = config_of(cfg_json)
    return [res for k in tile_keys if (res := run(TileId.from_key(k), cfg, wd)) is not None]


@stage_task(CLASSIFY)
def classify_task(tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """Grade the pairs of a batch of tiles (MS3DQE-Net); one summary per tile that has a live store."""
    from tasks.classify import run_classify_tile

    return _per_tile(run_classify_tile, tile_keys, cfg_json)


@stage_task(REGIONS)
def regions_task(cfg_json: dict) -> dict:
    """Plan the bad regions of the campus: {"status", "regions": [keys], "weights": [bytes per key], ...}."""
    from tasks.regions import run_regions_unit

    return run_regions_unit(*config_of(cfg_json))


@stage_task(REPAIR)
def repair_task(region_keys: list[str], cfg_json: dict) -> list[dict]:
    """Repair a batch of regions (fuse -> mesh -> stitch -> texture), one summary each."""
    from storage.contracts.region_plan import read_plan
    from tasks.repair import run_region

    cfg, wd = config_of(cfg_json)
    cfg = local_view(cfg, "texture")  # cameras and images by URL: this worker's staged copies
    plan = {r.key: r for r in read_plan(wd.root)}  # once per batch, not once per region
    return [run_region(k, cfg, wd, plan) for k in region_keys]


@stage_task(MERGE)
def merge_task(tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """Merge a batch of tiles into one clean mesh each (retained faces + rebuilt regions)."""
    from tasks.merge import run_merge_tile

    return _per_tile(run_merge_tile, tile_keys, cfg_json)


@stage_task(EXPORT)
def export_nodes_task(jobs: list, cfg_json: dict | None = None) -> list[dict]:
    """Build a batch of 3D Tiles nodes ((index, job) pairs); one {"index", "status", "record" | "error"} each.
    cfg_json: with a work dir by URL, the jobs' paths are relative to the work dir (``SyncExecutor`` sends them
    so) and the nodes are built on this process's mirror."""
    from pathlib import Path

    from tasks.export import build_nodes, relocate_jobs

    if cfg_json is not None and is_remote(cfg_json.get("work_dir")):
        jobs = relocate_jobs(jobs, Path(), mirror_for(cfg_json["work_dir"]).root)
    return build_nodes(jobs)


@stage_task(QUALITY)
def quality_task(cfg_json: dict, plan: dict, part: tuple) -> dict:
    """One share of the model's quality against the truth: {"status", "sums": {model: partial sums}}."""
    from tasks.quality import run_quality_share, share_name

    cfg, wd = config_of(cfg_json)
    plan = local_truth_plan(cfg, plan)  # a truth by URL: this worker's staged copy
    return record_step(wd, "quality", share_name(part),
                       lambda: {"sums": run_quality_share(cfg, wd, plan, tuple(part))})


@stage_task(HELDOUT_STAGE)
def heldout_task(cfg_json: dict) -> dict:
    """The held-out MLS strips measured against the input mesh and the merged model (``report/holdout.json``)."""
    from tasks.quality import run_heldout

    cfg, wd = config_of(cfg_json)
    return record_step(wd, "holdout", "campus", lambda: run_heldout(cfg, wd))


@stage_task(RENDERS_STAGE)
def region_renders_task(cfg_json: dict) -> dict:
    """Draw the rebuilt regions' before/after renders for the report, beside the export."""
    from tasks.report import run_region_renders

    return run_region_renders(*config_of(cfg_json))


@stage_task(REPORT)
def report_task(cfg_json: dict) -> dict:
    """Write the run report (``output/report.html``)."""
    from tasks.report import run_report_unit

    return run_report_unit(*config_of(cfg_json))
