"""Workers restarted between stages when earlier stages left them holding memory (a later stage's
peak must count its own memory), and left alone when they hold little."""

from __future__ import annotations

import pytest
from prefect import flow, task
from prefect.cache_policies import NONE as NO_CACHE

from flows.executors import InlineExecutor, PrefectExecutor

_HELD: list = []


@task(cache_policy=NO_CACHE)
def hold(mb: int) -> float:
    """Keep ``mb`` of touched memory in this worker process (as a stage's leftovers would); its RSS after."""
    import numpy as np
    import psutil

    _HELD.append(np.ones(mb * 2**20, np.uint8))
    return psutil.Process().memory_info().rss / 2**20


@task(cache_policy=NO_CACHE)
def rss() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


@flow
def _stages(over_mb: float, hold_mb: int) -> dict:
    ex = PrefectExecutor(progress=False)
    before = max(hold.submit(hold_mb).result(), hold.submit(hold_mb).result())
    slots = ex.slots()  # what the cluster has: the repair's batches are sized by it
    rec = ex.recycle_workers(over_mb)
    after = max(rss.submit().result(), rss.submit().result())
    return {"before": before, "after": after, "slots": slots, **rec}


@pytest.mark.parametrize("hold_mb, over_mb, restarted", [(400, 300, True), (0, 2048, False)])
def test_workers_holding_more_than_the_threshold_restart(prefect_api, tmp_path, hold_mb, over_mb, restarted):
    from prefect_dask import DaskTaskRunner

    from flows.runtime import embedded_prefect, local_cluster_kwargs

    runner = DaskTaskRunner(cluster_kwargs=local_cluster_kwargs(2, 1, "3GB"))
    with embedded_prefect(tmp_path, prefect_api):  # the session's server, as run_campus uses it
        out = _stages.with_options(task_runner=runner)(over_mb, hold_mb)
    assert (out["restarted"] > 0) == restarted, out
    assert out["slots"] == 2, out  # 2 workers of 1 thread
    if restarted:  # the leftovers are gone: a fresh worker holds far less than the one that held them
        assert out["largest_mb"] > over_mb and out["after"] < out["before"] - 300, out
    else:
        assert out["after"] < over_mb, out


def test_inline_runs_have_no_workers_to_restart():
    assert InlineExecutor().recycle_workers(0.0)["restarted"] == 0
    assert InlineExecutor().slots() == 0  # the config's worker count decides


def test_repair_batches_follow_the_cluster_not_the_config():
    """An external cluster of 6 slots gets 4 x 6 repair batches though the config says 2 workers."""
    from flows.campus import _Run
    from tasks.config import CampusConfig
    from tasks.repair import STAGE

    class Six(InlineExecutor):
        def slots(self) -> int:
            return 6

    cfg = CampusConfig.model_validate({"work_dir": "w"})
    assert cfg.cluster.n_workers == 2
    keys = [f"r{k:016x}" for k in range(100)]

    class T:
        spec = STAGE

    for ex, n in ((Six(), 24), (InlineExecutor(), 8)):
        run = _Run(cfg, {}, None, ex)
        assert len(run.batches(T, keys, workers=run.cluster_slots())) == n


def _malloc_env() -> dict:
    import os

    return {k: os.environ.get(k) for k in ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_THRESHOLD_")}


def test_local_workers_start_with_the_heap_settings_and_keep_them_after_a_restart():
    """Dask's own MALLOC_TRIM_THRESHOLD_=65536 pinned glibc's mmap threshold at 128 kB (a third more time in
    numpy-heavy units, all of it page faults): the local workers start with WORKER_MALLOC_ENV instead."""
    from distributed import Client, LocalCluster

    from flows.runtime import WORKER_MALLOC_ENV, local_cluster_kwargs

    kw = {**local_cluster_kwargs(1, 1, "1GB"), "preload": []}
    with LocalCluster(**kw) as cluster, Client(cluster) as client:
        assert list(client.run(_malloc_env).values()) == [WORKER_MALLOC_ENV]
        client.restart()  # what recycle_workers does before merge
        assert list(client.run(_malloc_env).values()) == [WORKER_MALLOC_ENV]


def test_the_local_scheduler_starts_with_the_long_tasks_durations():
    """Before a prefix has run, Dask assumes 0.5 s per task and queued both of the demo's 13 s export leaves on
    one worker while the other idled: the local cluster's scheduler (in this process) starts from
    the declared durations instead, and keeps the durations Dask sets itself."""
    import dask
    from distributed.scheduler import TaskPrefix

    from flows.runtime import local_cluster_kwargs, task_durations

    with dask.config.set({"distributed.scheduler.default-task-durations": {"other_task": "2s"}}):
        local_cluster_kwargs(1, 1, "1GB")
        assert TaskPrefix("quality_task").duration_average == 30.0
        assert TaskPrefix("export_nodes_task").duration_average == 5.0
        assert TaskPrefix("other_task").duration_average == 2.0
        assert task_durations() == {
            "quality_task": "30s", "heldout_task": "30s", "region_renders_task": "15s", "export_nodes_task": "5s"
        }
        assert set(task_durations()) <= set(dask.config.get("distributed.scheduler.default-task-durations"))
