"""The campus flow: scan -> register (while meshes ingest) -> ingest points -> prune -> partition +
labels per tile -> patch outliers -> classify per tile -> plan bad regions -> repair per region ->
merge per tile -> 3D Tiles export (nodes mapped) beside the quality shares -> run report.

Per-file and per-tile stages are mapped over a Dask cluster with ``prefect_dask.DaskTaskRunner`` (a
local cluster by default, an existing one by address). Tasks receive ids, paths, small JSON records and
the config, never arrays; every stage's outputs live in the work dir, and each unit is skipped when its
manifest record is done with matching fingerprints (``tasks.units.run_unit``), so re-running resumes.
Each stage is planned in this process first (``flows.planned``: its task function under
``tasks.units.planning``, one read of the stage's records) and only the units that must run become task
runs: a rerun with nothing changed launches none (and so starts no Dask cluster).

Expected failures (a bad input, a full disk) come back from tasks as failed unit summaries, not as
exceptions: the user sees each once, in the summary and in ``ms3d status``; Prefect's logs keep the
tracebacks of anything unexpected.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field

import numpy as np
from prefect import flow
from prefect.artifacts import create_table_artifact

from flows.executors import InlineExecutor, PrefectExecutor
from flows.planned import map_pending, pending, submit_pending
from flows.remote import SyncExecutor, is_remote, local_view, remote_run, work_dir_of
from flows.summary import CampusRunFailed, summarise
from flows.tasks import (
    classify_task,
    config_of,
    export_nodes_task,
    heldout_task,
    ingest_task,
    merge_task,
    outliers_task,
    partition_task,
    quality_task,
    region_renders_task,
    regions_task,
    register_task,
    repair_task,
    report_task,
    scan_task,
)
from storage import recorded
from storage.contracts.staging import prune_staging
from storage.errors import InputError
from storage.patches.schema import FACES_FILE, POINTS_FILE
from storage.workdir.housekeeping import drop_unplanned_records, sweep_temporary_files, work_dir_lock
from storage.workdir.layout import WorkDir, write_campus
from storage.workdir.manifest import consolidate
from tasks.config import CampusConfig
from tasks.stages import BatchContext

log = logging.getLogger("ms3d.flow")
RECYCLE_OVER = 0.25  # restart the local workers before merge when one holds more than this share of the budget

__all__ = ["CampusRunFailed", "InlineExecutor", "make_task_runner", "reprocess_from_config", "run_campus",
           "scan_inputs", "store_sizes"]


@flow(name="reprocess-campus", log_prints=True)
def _campus_flow(cfg_json: dict, progress: bool = True) -> dict:
    """The campus run of ``cfg_json`` as a Prefect flow on the flow's task runner (see the module docstring)."""
    cfg, _ = config_of(cfg_json)
    return _run_locked(cfg, PrefectExecutor(progress), publish=_publish_artifact)


def _run_locked(cfg: CampusConfig, ex, publish=None) -> dict:
    """The campus run on an executor, holding the work dir (its lock, or on a bucket its lease). Raises
    CampusRunFailed when units failed or the campus is incomplete."""
    wd = work_dir_of(cfg)
    with remote_run(cfg) if is_remote(cfg) else work_dir_lock(wd) as mirror:  # a URL: lease, sweep, pull
        ex = SyncExecutor(ex, mirror) if mirror is not None else ex
        summary = _run_stages(_Run(cfg, cfg.model_dump(mode="json"), wd, ex))
    if publish is not None:
        publish(summary)
    if summary["failed"] or summary["incomplete"]:
        raise CampusRunFailed(summary)
    return summary


def batcher(tsk, ctx: BatchContext):
    """units -> batches by the rule ``tsk``'s stage declares (``tsk.spec.batch``)."""
    return lambda units: tsk.spec.batch(units, ctx)


def scan_inputs(cfg: CampusConfig, wd: WorkDir, ex) -> tuple:
    """Discover and scan every input file (once per content), then choose the campus frame.

    Returns (records: list[InputFile], frame: CampusFrame, discovery, {path: source id}, scan summaries).
    """
    from tasks.scan import campus_frame, scan_files, scanned_records

    found, ids, files = scan_files(cfg)
    scans = map_pending(wd, ex, scan_task, files, "scan", batcher(scan_task, BatchContext(cfg.cluster.n_workers)),
                        cfg_json=cfg.model_dump(mode="json"))
    records = scanned_records([files], scans)
    return records, campus_frame(records, cfg), found, ids, scans


@dataclass
class _Run:
    """One campus run: its config, work dir and executor, the failures noted so far ({what: one line})
    and the unit summaries of each mapped stage."""

    cfg: CampusConfig
    cfg_json: dict
    wd: WorkDir
    ex: object
    failed: dict[str, str] = field(default_factory=dict)
    stages: dict[str, list[dict]] = field(default_factory=dict)

    @property
    def n_workers(self) -> int:
        return max(self.cfg.cluster.n_workers, 1)

    def cluster_slots(self) -> int:
        """The task slots the cluster has now (its workers' threads), else ``cluster.n_workers``."""
        return max(getattr(self.ex, "slots", lambda: 0)() or self.n_workers, 1)

    def batches(self, tsk, units: list, weights: dict | None = None, workers: int | None = None) -> list[list]:
        """``units`` of ``tsk``'s stage as task batches, by the rule its declaration names; workers: the
        worker count the rule sizes for (default ``cluster.n_workers``)."""
        return self.batcher(tsk, weights, workers)(units)

    def batcher(self, tsk, weights: dict | None = None, workers: int | None = None):
        """units -> batches for ``tsk``'s stage (``tsk.spec.batch``) in this run's context."""
        return batcher(tsk, BatchContext(workers or self.n_workers, self.cfg.cluster.tiles_per_task, weights or {}))

    def note(self, label: str, results: list[dict], per_unit: bool = True) -> list[dict]:
        """Note every failed summary of ``results`` as "<label> <unit>" (or ``label`` alone for a
        campus-wide step, first error kept); returns ``results``."""
        for s in results:
            if s.get("status") == "failed":
                self.failed.setdefault(f"{label} {s['unit']}" if per_unit else label, s["error"])
        return results


def _run_stages(run: _Run) -> dict:
    """Inputs, tiles, outputs; then the run summary (failures, per-stage counts, output paths)."""
    t_wall, t_start = time.perf_counter(), time.time()
    sweep_temporary_files(run.wd)
    inputs = _inputs(run)
    outliers = _tiles(run, inputs)
    exported, report = _outputs(run)
    consolidate(run.wd)
    summary = summarise(run.wd, time.perf_counter() - t_wall, run.failed, outliers, since=t_start,
                        stages=run.stages, incomplete=inputs["incomplete"],
                        skipped_files=list(inputs["found"].skipped), registration=inputs["registration"])
    summary["task_runs"] = getattr(run.ex, "task_runs", 0)
    summary["output"] = {"tileset": str(run.wd.tileset_json)
                         if exported["status"] == "done" else None, "report": report.get("report")}
    return summary


def _inputs(run: _Run) -> dict:
    """Scan, register (once, while the meshes are routed: mesh ingest needs the frame only), ingest the
    points; then note the bad inputs and prune whatever the plan no longer names."""
    from tasks.ingest import blocked_tiles, plan_units
    from tasks.scan import files_outside_box, points_box

    cfg, wd, ex = run.cfg, run.wd, run.ex
    records, frame, found, ids, scans = scan_inputs(cfg, wd, ex)
    rec_json = [r.to_json() for r in records]
    box = points_box(records, cfg.inputs.points_bounds, cfg.grid())  # inputs.points_bounds; None: every point
    left_out = files_outside_box(records, box)  # a box that misses every point file: one line, before registering
    if left_out:
        log.warning("inputs.points_bounds: %d point file(s) outside the box, not ingested: %s", len(left_out),
                    ", ".join(left_out[:5]) + (" ..." if len(left_out) > 5 else ""))
    reg_future = submit_pending(wd, ex, register_task, rec_json, frame.to_json(), run.cfg_json)
    units = plan_units(records, cfg.tiling.chunk_points, box)
    ingest_consts = {"cfg_json": run.cfg_json, "frame_json": frame.to_json()}
    mesh_units = [u for u in units if u.kind == "mesh"]
    todo, mesh_done = pending(wd, ingest_task, [u.to_json() for u in mesh_units], "ingest meshes",
                              **ingest_consts, matrix=None)
    mesh_ingest = ex.map(ingest_task, run.batches(ingest_task, todo), "ingest meshes", **ingest_consts, matrix=None)
    registration = reg_future.result()
    if "error" in registration:
        mesh_ingest.results()
        raise InputError(None, f"registration failed: {registration['error']}")
    write_campus(wd, frame, registration, run.cfg_json,
                 extra={"name": cfg.name, "inputs": rec_json, "grid": cfg.grid().to_json(),
                        "skipped_files": [list(s) for s in found.skipped]})
    matrix = np.asarray(registration["matrix"], np.float64)
    point_ingest = map_pending(wd, ex, ingest_task, [u.to_json() for u in units if u.kind == "points"],
                               "ingest points", run.batcher(ingest_task), **ingest_consts,
                               matrix=matrix.tolist())
    ingests = [r for rs in mesh_done.values() for r in rs] + mesh_ingest.results() + point_ingest
    blocked, failed, incomplete = blocked_tiles(records, ingests, units, frame, matrix, cfg.grid(), box)
    run.failed.update(failed)
    run.stages |= {"scan": scans, "ingest": ingests}
    prune_staging(wd, {u.key for u in units})
    drop_unplanned_records(wd, "ingest", {u.key for u in units})
    drop_unplanned_records(wd, "scan", {f"{s:08x}" for s in ids.values()})
    return {"records": records, "frame": frame, "found": found, "matrix": matrix, "blocked": blocked,
            "incomplete": incomplete, "registration": registration, "points_box": box}


def store_sizes(wd: WorkDir, tiles: list[str]) -> dict[str, int]:
    """{tile key: bytes of its points and faces stores}, the classify stage's weights (its largest stores start
    first: one long unit no longer runs alone on the last worker). A store that cannot be read counts as empty."""
    def size(key: str) -> int:  # on a bucket: the recorded sizes, nothing downloaded
        return sum(st.size for name in (POINTS_FILE, FACES_FILE)
                   if (st := recorded.state(wd.root / "tiles" / key / name)) is not None)

    return {k: size(k) for k in tiles}


def _tiles(run: _Run, inputs: dict) -> dict:
    """Partition (+ labels) every planned tile, fit the patch outliers, grade every pair (MS3DQE-Net),
    plan the bad regions over the campus, rebuild each region, merge each tile. Returns the outlier fit."""
    from tasks.ingest import input_tiles
    from tasks.repair import pending_regions

    cfg, wd, ex, cj = run.cfg, run.wd, run.ex, run.cfg_json
    hints = input_tiles(inputs["records"], inputs["frame"], inputs["matrix"], cfg.grid(), inputs["points_box"])
    tiles = sorted({k for h in hints.values() for k in h} | {t.key for t in wd.staged_tiles()}
                   | set(wd.tile_keys_on_disk()))
    parts = run.note("tile", map_pending(wd, ex, partition_task, tiles, "partition", run.batcher(partition_task), cfg_json=cj,
                                         frame_json=inputs["frame"].to_json(), blocked=inputs["blocked"]))
    run.note("labels", [{"status": "failed", "unit": s["unit"], "error": s["labels_error"]}
                        for s in parts if s.get("labels_error")])
    drop_unplanned_records(wd, "partition", set(tiles))
    drop_unplanned_records(wd, "labels", set(tiles))
    outliers = submit_pending(wd, ex, outliers_task, cj).result()
    run.note("outliers", [outliers], per_unit=False)
    grades = run.note("classify", map_pending(wd, ex, classify_task, tiles, "classify",
                                              run.batcher(classify_task, store_sizes(wd, tiles)), cfg_json=cj))
    drop_unplanned_records(wd, "classify", set(tiles))
    plan = submit_pending(wd, ex, regions_task, cj).result()
    run.note("regions", [plan], per_unit=False)
    todo, unchanged = pending_regions(plan["regions"], local_view(cfg, "cameras"), wd)  # one read of the plan, records
    region_batches = run.batches(repair_task, todo, dict(zip(plan["regions"], plan["weights"])),
                                 workers=run.cluster_slots())  # an external cluster's real size
    repairs = run.note("region", unchanged + ex.map(repair_task, region_batches, "repair", cfg_json=cj).results())
    if not cfg.cluster.address:  # our own workers: what classify and repair left must not count against merge
        rec = ex.recycle_workers(RECYCLE_OVER * cfg.partition.memory_budget_mb)
        if rec["restarted"]:
            log.info("restarted %d workers before merge (one held %.0f MB)", rec["restarted"], rec["largest_mb"])
    merges = run.note("merge", map_pending(wd, ex, merge_task, tiles, "merge", run.batcher(merge_task), cfg_json=cj))
    drop_unplanned_records(wd, "merge", set(tiles))
    run.stages |= {"partition": parts, "classify": grades, "repair": repairs, "merge": merges}
    return outliers


def _outputs(run: _Run) -> tuple[dict, dict]:
    """3D Tiles (nodes mapped over the workers) beside the model's quality shares, then the run report.
    Returns (export summary, report summary)."""
    from tasks.export import node_records, run_export_stage
    from tasks.quality import heldout_pending, quality_parts, quality_plan, share_name, write_quality
    from tasks.report import region_renders_fresh

    cfg, wd, ex, cj = run.cfg, run.wd, run.ex, run.cfg_json

    side: dict = {}

    # the report's figures, drawn beside the export's upper levels (one node each, a core idle). Submitted beside
    # the leaves, they took the first worker whose own queue ran dry while the other still had leaves queued (a
    # queued task does not move for a priority): the leaves' level ended ~10 s later on the 384 M-point campus
    def start_renders() -> None:
        if "renders" not in side:
            side["renders"] = ex.submit(region_renders_task, cj) \
                if cfg.report.enabled and not region_renders_fresh(cfg, wd) else None

    def map_jobs(jobs: list) -> list[dict]:  # one level of the quadtree at a time; records in job order
        mapped = ex.map(export_nodes_task, run.batches(export_nodes_task, jobs), "export")
        if side.get("leaves_built"):  # queued behind the level above the leaves: a worker takes them when it
            start_renders()           # has no node left, beside the upper levels and the driver's points overlay
        done = mapped.results()
        side["leaves_built"] = True
        return node_records(done, len(jobs))

    qplan = quality_plan(local_view(cfg, "truth"), wd) if cfg.report.enabled and cfg.report.quality else None
    parts = quality_parts(qplan, run.n_workers)
    shares = [ex.submit(quality_task, cj, qplan, part) for part in parts]
    held = ex.submit(heldout_task, cj) if cfg.report.enabled and heldout_pending(cfg, wd) else None
    exported = run_export_stage(cfg, wd, map_jobs=map_jobs)
    start_renders()  # when the export built no node, or one level only
    renders = side["renders"]
    if shares:  # the model against the truth, measured beside the export
        got = run.note("quality", [s.result() for s in shares], per_unit=False)
        if not any(g.get("status") == "failed" for g in got):
            write_quality(wd, qplan["key"], [g["sums"] for g in got])
            drop_unplanned_records(wd, "quality", {share_name(p) for p in parts})
    run.note("export", [exported], per_unit=False)
    if held is not None:  # the held-out MLS strips against the input mesh and the merged model
        run.note("holdout", [held.result()], per_unit=False)
    if renders is not None:
        try:
            got = renders.result()
        except Exception as e:  # noqa: BLE001 - the report draws them itself and says why not
            got = {"status": "failed", "error": f"{type(e).__name__}: {e}"}
        if got.get("status") == "failed":
            log.warning("region renders: %s (the report draws them)", got["error"])
    report = submit_pending(wd, ex, report_task, cj).result() if cfg.report.enabled else {"status": "skipped"}
    run.note("report", [report], per_unit=False)
    return exported, report


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
    from flows.runtime import local_cluster_kwargs  # 127.0.0.1 only, no dashboard

    return DaskTaskRunner(cluster_kwargs=local_cluster_kwargs(
        cfg.cluster.n_workers, cfg.cluster.threads_per_worker, cfg.cluster.memory_limit))


def run_campus(cfg: CampusConfig, progress: bool = True, executor=None) -> dict:
    """Reprocess a campus: the one entry point of a run (the CLI's ``ms3d run``, ``ms3d demo``, training and
    evaluation call it). The campus flow runs with one embedded Prefect API (unless one is configured) and a
    Dask cluster; ``runner: inline`` in the config, or an ``executor`` (:class:`InlineExecutor`, or a test's),
    runs the stages in this process without Prefect. Returns the run summary; raises CampusRunFailed when
    units failed or the campus is incomplete."""
    if executor is not None:
        return _run_locked(cfg, executor)
    from flows.runtime import embedded_prefect
    from storage.workdir.housekeeping import check_work_dir_writable

    wd = work_dir_of(cfg)  # a work dir by URL: this process's mirror (flows.remote)
    check_work_dir_writable(wd)
    if cfg.runner == "inline":
        return _run_locked(cfg, InlineExecutor())
    with embedded_prefect(wd.prefect_dir, cfg.cluster.prefect_api_url):
        log.info("Prefect API up %.1f s after the process started", _since_process_start())
        runner = make_task_runner(cfg)
        return _campus_flow.with_options(task_runner=runner)(cfg.model_dump(mode="json"), progress=progress)


def _since_process_start() -> float:
    """Seconds since this process started (NaN when unknown)."""
    try:
        import psutil

        return time.time() - psutil.Process().create_time()
    except Exception:  # noqa: BLE001 - a figure for the log only
        return float("nan")


@flow(name="reprocess-campus-from-config")
def reprocess_from_config(config_path: str, overrides: dict | None = None) -> dict:
    """The entry point of a scheduled run (``deploy/prefect.yaml``, ``ms3d serve``): load a YAML config and
    reprocess its campus on the task runner the config names; the Prefect API is the deployment's server."""
    cfg = CampusConfig.from_yaml(config_path, overrides)
    return _campus_flow.with_options(task_runner=make_task_runner(cfg))(cfg.model_dump(mode="json"), progress=False)
