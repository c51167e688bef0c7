"""The campus flow: scan -> register (while meshes ingest) -> ingest points -> prune -> partition +
labels per tile -> patch outliers -> classify per tile -> plan bad regions -> repair per region ->
merge per tile -> 3D Tiles export (nodes mapped) beside the quality shares -> run report.

Per-file and per-tile stages are mapped over a Dask cluster with ``prefect_dask.DaskTaskRunner`` (a
local cluster by default, an existing one by address). Tasks receive ids, paths, small JSON records and
the config, never arrays; every stage's outputs live in the work dir, and each unit is skipped when its
manifest record is done with matching fingerprints (``tasks.units.run_unit``), so re-running resumes.

Expected failures (a bad input, a full disk) come back from tasks as failed unit summaries, not as
exceptions: the user sees each once, in the summary and in ``ms3d status``; Prefect's logs keep the
tracebacks of anything unexpected.
"""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

from prefect import flow
from prefect.artifacts import create_table_artifact

from flows.classify import classify_task
from flows.executors import InlineExecutor, PrefectExecutor
from flows.stage_tasks import (
    _cfg,
    export_nodes_task,
    ingest_task,
    merge_task,
    outliers_task,
    partition_task,
    quality_task,
    regions_task,
    register_task,
    repair_task,
    report_task,
    scan_task,
)
from flows.summary import CampusRunFailed, summarise
from storage.errors import InputError
from storage.manifest import consolidate
from storage.workdir import WorkDir
from tasks.config import CampusConfig

log = logging.getLogger("ms3d.flow")

__all__ = ["CampusRunFailed", "InlineExecutor", "make_task_runner", "reprocess_campus", "reprocess_from_config",
           "run_campus", "scan_inputs"]

# ------------------------------------------------------------------------------------------ planning


def balanced_batches(items: list, weights: list[float], n_batches: int) -> list[list]:
    """Split items into at most ``n_batches`` batches of about equal total weight (largest first,
    greedy), each batch in input order. Task runs cost ~0.3 s each: a thousand small files must not
    become a thousand tasks."""
    n = max(1, min(n_batches, len(items)))
    order = sorted(range(len(items)), key=lambda i: -weights[i])
    loads, members = [0.0] * n, [[] for _ in range(n)]
    for i in order:
        b = loads.index(min(loads))
        loads[b] += weights[i]
        members[b].append(i)
    return [[items[i] for i in sorted(m)] for m in members if m]


def _batches(items: list, size: int) -> list[list]:
    return [items[i:i + size] for i in range(0, len(items), size)]


# ------------------------------------------------------------------------------------------ flow


@flow(name="reprocess-campus", log_prints=True)
def reprocess_campus(cfg_json: dict, progress: bool = True) -> dict:
    """Scan -> register -> ingest -> partition (+ labels) -> outliers over the campus of ``cfg_json``."""

    cfg = _cfg(cfg_json)
    return reprocess(cfg, PrefectExecutor(progress), publish=_publish_artifact)


def reprocess(cfg: CampusConfig, ex, publish=None) -> dict:
    """The campus run on an executor (:class:`PrefectExecutor` inside the flow, :class:`InlineExecutor`
    for a run without Prefect). Raises CampusRunFailed when units failed or the campus is incomplete."""
    from storage.housekeeping import work_dir_lock

    wd = WorkDir(cfg.work_dir)
    with work_dir_lock(wd):
        summary = _reprocess(cfg, cfg.model_dump(mode="json"), wd, ex)
    if publish is not None:
        publish(summary)
    if summary["failed"] or summary["incomplete"]:
        raise CampusRunFailed(summary)
    return summary


def scan_inputs(cfg: CampusConfig, wd: WorkDir, ex) -> tuple:
    """Discover and scan every input file (once per content), then choose the campus frame.

    Returns (records: list[InputFile], frame: CampusFrame, discovery, {path: source id}, scan summaries).
    """
    from storage.inputs import InputFile, assign_source_ids, discover
    from tasks.scan.stage import campus_frame

    cfg_json = cfg.model_dump(mode="json")
    n_workers = max(cfg.cluster.n_workers, 1)
    found = discover(cfg.inputs.mesh, cfg.inputs.points)
    if cfg.inputs.labels and not Path(cfg.inputs.labels).is_file():
        raise InputError(cfg.inputs.labels, "labels file not found (inputs.labels in the config)")
    ids = assign_source_ids(list(found.meshes) + list(found.points))
    files = [{"path": p, "kind": "mesh", "source": ids[p]} for p in found.meshes] + \
            [{"path": p, "kind": "points", "source": ids[p]} for p in found.points]
    sizes = [_size(f["path"]) * (20 if f["kind"] == "mesh" else 1) for f in files]  # meshes are read whole
    scan_batches = balanced_batches(files, sizes, 4 * n_workers)
    scans = ex.map(scan_task, scan_batches, "scan", cfg_json=cfg_json).results()
    records = []
    for f, s in zip([f for b in scan_batches for f in b], scans):
        rec = s.get("record") or InputFile(f["source"], f["path"], f["kind"], "", error=s.get("error", "scan failed")).to_json()
        records.append(InputFile(**rec))
    return records, campus_frame(records, cfg), found, ids, scans


def _reprocess(cfg: CampusConfig, cfg_json: dict, wd: WorkDir, ex) -> dict:
    import numpy as np

    from storage.workdir import write_campus
    from tasks.export.stage import run_export_stage
    from tasks.ingest.stage import plan_units, prune_staging, tiles_hint
    from storage.housekeeping import drop_unplanned_records, sweep_temporary_files

    t_wall, t_start = time.perf_counter(), time.time()
    n_workers = max(cfg.cluster.n_workers, 1)
    sweep_temporary_files(wd)

    records, frame, found, ids, scans = scan_inputs(cfg, wd, ex)
    grid = cfg.grid()

    # register (once) while the meshes are routed: mesh ingest needs the frame only
    rec_json = [r.to_json() for r in records]
    reg_future = ex.submit(register_task, rec_json, frame.to_json(), cfg_json)
    units = plan_units(records, cfg.tiling.chunk_points)
    mesh_units = [u for u in units if u.kind == "mesh"]
    point_units = [u for u in units if u.kind == "points"]
    mesh_batches = balanced_batches([u.to_json() for u in mesh_units],
                                    [_size(u.path) for u in mesh_units], 4 * n_workers)
    mesh_ingest = ex.map(ingest_task, mesh_batches, "ingest meshes", cfg_json=cfg_json, frame_json=frame.to_json(),
                         matrix=None)
    registration = reg_future.result()
    if "error" in registration:
        mesh_ingest.results()
        raise InputError(None, f"registration failed: {registration['error']}")
    write_campus(wd, frame, registration, cfg.model_dump(mode="json"),
                 extra={"name": cfg.name, "inputs": rec_json, "grid": grid.to_json(),
                        "skipped_files": [list(s) for s in found.skipped]})
    matrix = np.asarray(registration["matrix"], np.float64)
    point_batches = _batches([u.to_json() for u in point_units], 1)
    point_ingest = ex.map(ingest_task, point_batches, "ingest points", cfg_json=cfg_json, frame_json=frame.to_json(),
                          matrix=matrix.tolist())
    ingests = mesh_ingest.results() + point_ingest.results()

    # what each bad input blocks: the tiles its bounds cover; unknown bounds make the campus incomplete
    by_source = {r.source: r for r in records}
    hints = {r.source: tiles_hint(r, frame, matrix, grid) for r in records}
    blocked: dict[str, str] = {}
    failed: dict[str, str] = {}
    incomplete: list[str] = []
    bad_inputs = [(r, r.error) for r in records if r.error]
    unit_src = {u.key: u.source for u in units}
    bad_inputs += [(by_source[unit_src[s["unit"]]], s["error"]) for s in ingests
                   if s["status"] == "failed" and s["unit"] in unit_src]
    for r, err in bad_inputs:
        failed[f"input {r.name}"] = err
        if not hints[r.source]:
            incomplete.append(r.path)
        for tk in hints[r.source]:
            blocked.setdefault(tk, f"blocked: its input {r.name} failed (see that input's error)")

    # the plan names the staging files and tiles that should exist; everything else goes
    prune_staging(wd, {u.key for u in units})
    drop_unplanned_records(wd, "ingest", {u.key for u in units})
    drop_unplanned_records(wd, "scan", {f"{s:08x}" for s in ids.values()})
    tiles = sorted({k for h in hints.values() for k in h} | {t.key for t in wd.staged_tiles()}
                   | set(wd.tile_keys_on_disk()))
    tile_batches = _batches(tiles, cfg.cluster.tiles_per_task)
    parts = ex.map(partition_task, tile_batches, "partition", cfg_json=cfg_json, frame_json=frame.to_json(),
                   blocked=blocked).results()
    for s in parts:
        if s["status"] == "failed":
            failed[f"tile {s['unit']}"] = s["error"]
        elif s.get("labels_error"):
            failed[f"labels {s['unit']}"] = s["labels_error"]
    drop_unplanned_records(wd, "partition", set(tiles))
    drop_unplanned_records(wd, "labels", set(tiles))

    outliers = ex.submit(outliers_task, cfg_json).result()

    # grade every pair (MS3DQE-Net), plan the bad regions over the campus, rebuild each region
    grades = ex.map(classify_task, tile_batches, "classify", cfg_json=cfg_json).results()
    for s in grades:
        if s["status"] == "failed":
            failed[f"classify {s['unit']}"] = s["error"]
    drop_unplanned_records(wd, "classify", set(tiles))
    plan = ex.submit(regions_task, cfg_json).result()
    if plan["status"] == "failed":
        failed["regions"] = plan["error"]
    region_batches = balanced_batches(plan["regions"], plan["weights"], 4 * n_workers)
    repairs = ex.map(repair_task, region_batches, "repair", cfg_json=cfg_json).results()
    for s in repairs:
        if s["status"] == "failed":
            failed[f"region {s['unit']}"] = s["error"]

    # output: one clean mesh per tile, then 3D Tiles and the run report
    merges = ex.map(merge_task, tile_batches, "merge", cfg_json=cfg_json).results()
    for s in merges:
        if s["status"] == "failed":
            failed[f"merge {s['unit']}"] = s["error"]
    drop_unplanned_records(wd, "merge", set(tiles))
    from tasks.report.stage import quality_plan, write_quality

    qplan = quality_plan(cfg, wd) if cfg.report.enabled and cfg.report.quality else None
    shares = [ex.submit(quality_task, cfg_json, qplan, (k, n_workers)) for k in range(n_workers)] if qplan else []
    exported = run_export_stage(cfg, wd, map_jobs=lambda jobs: _map_export_jobs(ex, jobs, n_workers))
    if shares:  # the model against the truth, measured beside the export in n_workers shares
        got = [s.result() for s in shares]
        bad = [g["error"] for g in got if g.get("status") == "failed"]
        if bad:
            failed["quality"] = bad[0]
        else:
            write_quality(wd, qplan["key"], [g["sums"] for g in got])
    if exported["status"] == "failed":
        failed["export"] = exported["error"]
    report = ex.submit(report_task, cfg_json).result() if cfg.report.enabled else {"status": "skipped"}
    if report["status"] == "failed":
        failed["report"] = report["error"]
    consolidate(wd)
    summary = summarise(wd, time.perf_counter() - t_wall, failed, outliers, since=t_start,
                        stages={"scan": scans, "ingest": ingests, "partition": parts, "classify": grades,
                                "repair": repairs, "merge": merges},
                        incomplete=incomplete, skipped_files=list(found.skipped),
                        registration=registration)
    summary["task_runs"] = getattr(ex, "task_runs", 0)
    summary["output"] = {"tileset": str(wd.root / "output" / "tileset.json") if exported["status"] == "done" else None,
                         "report": report.get("report")}
    return summary


def _map_export_jobs(ex, jobs: list, n_workers: int) -> list[dict]:
    """Build 3D Tiles nodes as mapped tasks (one level of the quadtree at a time); records in job order."""
    indexed = list(enumerate(jobs))
    batches = balanced_batches(indexed, [1.0] * len(indexed), 4 * n_workers)
    got = {r["index"]: r for r in ex.map(export_nodes_task, batches, "export").results() if "index" in r}
    bad = [r.get("error", "export task failed") for i, r in got.items() if r["status"] != "done"]
    if bad or len(got) != len(jobs):
        raise InputError(None, "; ".join(bad) or "an export task failed (see the run history)")
    return [got[i]["record"] for i in range(len(jobs))]


def _size(path: str) -> float:
    try:
        return float(Path(path).stat().st_size) + 1.0
    except OSError:
        return 1.0


def _publish_artifact(summary: dict) -> None:
    try:
        create_table_artifact(key="campus-tiles", table=summary["tile_rows"],
                              description=f"Per-tile counts and failures of {summary['work_dir']}")
    except Exception as e:  # noqa: BLE001 - an artifact is a convenience, never a reason to fail
        log.warning("could not publish the tile table artifact: %s", e)


# ------------------------------------------------------------------------------------------ runtime


def make_task_runner(cfg: CampusConfig):
    """A DaskTaskRunner for an existing cluster (``cluster.address``) or a new local one."""
    if cfg.runner in ("local", "inline"):
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=1)
    from prefect_dask import DaskTaskRunner

    if cfg.cluster.address:
        return DaskTaskRunner(address=cfg.cluster.address)
    return DaskTaskRunner(cluster_kwargs={
        "n_workers": cfg.cluster.n_workers, "threads_per_worker": cfg.cluster.threads_per_worker,
        "processes": True, "memory_limit": cfg.cluster.memory_limit, "dashboard_address": None,
    })


def run_campus(cfg: CampusConfig, progress: bool = True) -> dict:
    """Run the campus flow with one embedded Prefect API (unless one is configured) and a Dask cluster."""
    from flows.runtime import embedded_prefect
    from storage.housekeeping import check_work_dir_writable

    wd = WorkDir(cfg.work_dir)
    check_work_dir_writable(wd)
    if cfg.runner == "inline":
        return reprocess(cfg, InlineExecutor())
    with embedded_prefect(wd.prefect_dir, cfg.cluster.prefect_api_url):
        runner = make_task_runner(cfg)
        return reprocess_campus.with_options(task_runner=runner)(cfg.model_dump(mode="json"), progress=progress)


@flow(name="reprocess-campus-from-config")
def reprocess_from_config(config_path: str, overrides: dict | None = None) -> dict:
    """Deployment entry point: load a YAML config and reprocess its campus (uses the flow's task runner,
    configured in deploy/prefect.yaml; the Prefect API is the deployment's server)."""
    cfg = CampusConfig.from_yaml(config_path, overrides)
    return reprocess_campus.with_options(task_runner=make_task_runner(cfg))(cfg.model_dump(mode="json"), progress=False)
