"""The campus flow: register -> ingest (route to tiles) -> partition per tile -> patch outliers.

Per-unit and per-tile stages are mapped over a Dask cluster with ``prefect_dask.DaskTaskRunner`` (a
local cluster by default, an existing one by address). Tasks receive ids, paths and the config as
JSON, never arrays; every stage's outputs live in the work dir, and each task skips a unit whose
manifest record is done with matching fingerprints, so re-running resumes.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

from prefect import flow, task, unmapped
from prefect.artifacts import create_table_artifact
from prefect.cache_policies import NONE as NO_CACHE
from prefect.futures import as_completed

from storage.errors import InputError
from storage.manifest import consolidate
from storage.workdir import WorkDir
from tasks.config import CampusConfig

log = logging.getLogger("ms3d.flow")


class CampusRunFailed(RuntimeError):
    """Some units failed; the others are done and the manifest says which."""

    def __init__(self, summary: dict):
        self.summary = summary
        failed = summary["failed"]
        lines = [f"{len(failed)} unit(s) failed:"] + [f"  {u}: {e}" for u, e in list(failed.items())[:20]]
        super().__init__("\n".join(lines))

    def __reduce__(self):
        return (type(self), (self.summary,))


# ------------------------------------------------------------------------------------------ tasks


def _cfg(cfg_json: dict) -> CampusConfig:
    return CampusConfig.model_validate(cfg_json)


@task(name="register", cache_policy=NO_CACHE)
def register_task(cfg_json: dict) -> dict:
    from tasks.ingest import run_register

    cfg = _cfg(cfg_json)
    return run_register(cfg, WorkDir(cfg.work_dir))


@task(name="ingest", cache_policy=NO_CACHE)
def ingest_task(units: list[dict], cfg_json: dict) -> list[dict]:
    """Route a batch of ingest units; a bad unit fails this task after the others are done."""
    from storage.workdir import read_campus
    from tasks.ingest import IngestUnit, run_ingest_unit

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    campus = read_campus(wd)
    return _run_batch([IngestUnit(**u) for u in units], lambda u: run_ingest_unit(u, cfg, wd, campus), lambda u: u.key)


@task(name="partition", cache_policy=NO_CACHE)
def partition_task(tile_keys: list[str], cfg_json: dict, blocked: dict[str, str]) -> list[dict]:
    """Partition a batch of tiles into patch stores; a bad tile fails this task after the others are done."""
    from storage.ids import TileId
    from tasks.patches import run_partition_tile

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    return _run_batch([TileId.from_key(k) for k in tile_keys],
                      lambda t: run_partition_tile(t, cfg, wd, blocked.get(t.key)), lambda t: t.key)


@task(name="outliers", cache_policy=NO_CACHE)
def outliers_task(cfg_json: dict) -> dict:
    from tasks.patches import run_outliers

    cfg = _cfg(cfg_json)
    return run_outliers(cfg, WorkDir(cfg.work_dir))


def _run_batch(items, run, key) -> list[dict]:
    results, errors = [], []
    for it in items:
        try:
            results.append(run(it))
        except InputError as e:
            errors.append(f"{key(it)}: {e}")
    if errors:
        raise InputError(None, "; ".join(errors))
    return results


# ------------------------------------------------------------------------------------------ flow


@dataclass
class _Progress:
    """A terminal progress bar over futures (rich), silent when not a terminal."""

    label: str
    total: int
    enabled: bool = True
    _bar: object = field(default=None, repr=False)

    def __enter__(self):
        if self.enabled:
            from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

            self._bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn())
            self._bar.start()
            self._id = self._bar.add_task(self.label, total=self.total)
        return self

    def advance(self):
        if self._bar is not None:
            self._bar.advance(self._id)

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.stop()


def _batches(items: list, size: int) -> list[list]:
    return [items[i:i + size] for i in range(0, len(items), size)]


def _wait_all(futures, label: str, progress: bool) -> list:
    """Wait for every future; return their states in submission order."""
    with _Progress(label, len(futures), enabled=progress) as bar:
        for _ in as_completed(futures):
            bar.advance()
    for f in futures:
        f.wait()  # sets the future's final state from the Dask result, not from the (lagging) API
    return [f.state for f in futures]


@flow(name="reprocess-campus", log_prints=True)
def reprocess_campus(cfg_json: dict, progress: bool = True) -> dict:
    """Register -> ingest -> partition -> outliers over the campus of ``cfg_json`` (a CampusConfig)."""
    import numpy as np

    from storage.frame import CampusFrame
    from tasks.ingest import InputFile, plan_units, tiles_hint, unit_to_json

    cfg = _cfg(cfg_json)
    wd = WorkDir(cfg.work_dir)
    t_wall = time.perf_counter()
    t_start = time.time()
    campus = register_task.submit(cfg_json).result()

    inputs = [InputFile(**r) for r in campus["inputs"]]
    frame = CampusFrame.from_json(campus["frame"])
    matrix = np.asarray(campus["registration"]["matrix"])
    units = plan_units([r for r in inputs if not r.error or r.lo], cfg)
    hints = {r.index: tiles_hint(r, frame, matrix, cfg.tiling.tile_size_m) for r in inputs}
    all_hinted = sorted({k for h in hints.values() for k in h})

    unit_batches = _batches(units, 1)  # one ingest unit (a point range or a mesh file) per task
    ingest_futs = ingest_task.map([[unit_to_json(u) for u in b] for b in unit_batches], cfg_json=unmapped(cfg_json))
    states = _wait_all(ingest_futs, "ingest", progress)
    failed: dict[str, str] = {}
    blocked: dict[str, str] = {}
    for b, st in zip(unit_batches, states):
        if not st.is_completed():
            for u in b:
                err = _state_error(st)
                failed[f"ingest/{u.key}"] = err
                for tk in hints.get(u.file_index) or all_hinted:
                    blocked.setdefault(tk, f"input {Path(u.path).name} failed: {err}")
    for r in inputs:
        if r.error:
            failed[f"input/{Path(r.path).name}"] = r.error
            for tk in hints.get(r.index) or all_hinted:
                blocked.setdefault(tk, f"input {Path(r.path).name} failed: {r.error}")

    tiles = sorted(set(all_hinted) | {t.key for t in wd.staged_tiles()})
    tile_batches = _batches(tiles, cfg.cluster.tiles_per_task)
    part_futs = partition_task.map(tile_batches, cfg_json=unmapped(cfg_json), blocked=unmapped(blocked))
    states = _wait_all(part_futs, "partition", progress)
    for b, st in zip(tile_batches, states):
        if not st.is_completed():
            for msg in _state_error(st).split("; "):
                key, _, err = msg.partition(": ")
                if key in b:
                    failed[f"partition/{key}"] = err

    outliers = outliers_task.submit(cfg_json).result()
    consolidate(wd)
    summary = _summarise(wd, time.perf_counter() - t_wall, failed, outliers, since=t_start)
    _publish_artifact(summary)
    if failed:
        raise CampusRunFailed(summary)
    return summary


def _state_error(state) -> str:
    try:
        state.result()
    except Exception as e:  # noqa: BLE001 - the message is what we report
        return str(e)
    return state.message or "failed"


def _summarise(wd: WorkDir, wall_s: float, failed: dict, outliers: dict, since: float = 0.0) -> dict:
    from storage.manifest import all_records

    recs = all_records(wd)
    tiles = [r for r in recs if r.stage == "partition"]
    task_s = sum(r.seconds for r in recs if r.updated_at >= since)  # work done by this run only
    return {
        "work_dir": str(wd.root),
        "wall_seconds": wall_s,
        "task_seconds": task_s,
        "tiles_done": sorted(r.unit for r in tiles if r.status == "done"),
        "tiles_empty": sorted(r.unit for r in tiles if r.status == "empty"),
        "tiles_failed": sorted(r.unit for r in tiles if r.status == "failed"),
        "tile_rows": [{"tile": r.unit, "status": r.status, "points": r.summary.get("n_points", 0),
                       "faces": r.summary.get("n_faces", 0), "patches": r.summary.get("n_patches", 0),
                       "seconds": round(r.seconds, 2), "error": r.error[:200]} for r in tiles],
        "failed": failed,
        "outliers": outliers,
    }


def _publish_artifact(summary: dict) -> None:
    try:
        create_table_artifact(key="campus-tiles", table=summary["tile_rows"],
                              description=f"Per-tile counts and failures of {summary['work_dir']}")
    except Exception as e:  # noqa: BLE001 - an artifact is a convenience, never a reason to fail
        log.warning("could not publish the tile table artifact: %s", e)


# ------------------------------------------------------------------------------------------ runtime


def make_task_runner(cfg: CampusConfig):
    """A DaskTaskRunner for an existing cluster (``cluster.address``) or a new local one."""
    if cfg.runner == "local":
        from prefect.task_runners import ThreadPoolTaskRunner

        return ThreadPoolTaskRunner(max_workers=1)
    from prefect_dask import DaskTaskRunner

    if cfg.cluster.address:
        return DaskTaskRunner(address=cfg.cluster.address)
    return DaskTaskRunner(cluster_kwargs={
        "n_workers": cfg.cluster.n_workers, "threads_per_worker": cfg.cluster.threads_per_worker,
        "processes": True, "memory_limit": cfg.cluster.memory_limit, "dashboard_address": ":0",
    })


def run_campus(cfg: CampusConfig, progress: bool = True) -> dict:
    """Run the campus flow with one embedded Prefect API (unless one is configured) and a Dask cluster."""
    from flows.runtime import embedded_prefect

    wd = WorkDir(cfg.work_dir)
    wd.root.mkdir(parents=True, exist_ok=True)
    with embedded_prefect(wd.prefect_dir, cfg.cluster.prefect_api_url):
        runner = make_task_runner(cfg)
        return reprocess_campus.with_options(task_runner=runner)(cfg.model_dump(mode="json"), progress=progress)


@flow(name="reprocess-campus-from-config")
def reprocess_from_config(config_path: str, overrides: dict | None = None) -> dict:
    """Deployment entry point: load a YAML config and reprocess its campus (uses the flow's task runner,
    configured in deploy/prefect.yaml; the Prefect API is the deployment's server)."""
    cfg = CampusConfig.from_yaml(config_path, overrides)
    return reprocess_campus.with_options(task_runner=make_task_runner(cfg))(cfg.model_dump(mode="json"), progress=False)
