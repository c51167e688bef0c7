"""Operations, for real: a served schedule that fires, a Dask cluster started from the command line that
loses a worker to SIGKILL mid-partition, and ``kill -9`` of a whole ``ms3d run`` followed by a rerun.

Each case ends with the same check: the stores equal those of a clean run, and nothing a killed
attempt half-wrote is left behind."""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from flows.campus import InlineExecutor, run_campus
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import all_records
from tasks.config import CampusConfig

from .conftest import build_campus

pytestmark = pytest.mark.slow
REPO = Path(__file__).resolve().parents[2]


def _checksums(work: Path) -> dict[str, str]:
    """sha256 of every store file (tiles/*/*.parquet)."""
    return {str(p.relative_to(work)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted((work / "tiles").glob("*/*.parquet"))}


@pytest.fixture(scope="module")
def campus(tmp_path_factory) -> Path:
    """One hand-made campus (20 m tiles) for the module: its stores depend on the inputs' paths."""
    return build_campus(tmp_path_factory.mktemp("in"), tile_size_m=20.0)


@pytest.fixture(scope="module")
def clean_checksums(campus, tmp_path_factory) -> dict[str, str]:
    """The stores of a clean inline run of ``campus``, run once for the module."""
    work = tmp_path_factory.mktemp("clean")
    run_campus(CampusConfig.from_yaml(campus, {"work_dir": str(work), "runner": "inline"}), executor=InlineExecutor())
    return _checksums(work)


def _temporary_files(work: Path) -> list[Path]:
    return [p for p in work.rglob(".*") if ".tmp" in p.name]


def _free_port() -> int:
    with contextlib.closing(socket.socket()) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait(cond, timeout_s: float, what: str, period_s: float = 0.5):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        got = cond()
        if got:
            return got
        time.sleep(period_s)
    raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}")


def _env(**extra) -> dict:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", **{k: str(v) for k, v in extra.items()}}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def _stop(proc: subprocess.Popen, sig=signal.SIGTERM, timeout_s: float = 30) -> None:
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, sig)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _partition_records(work: Path) -> dict[str, float]:
    d = work / "manifest.d" / "partition"
    out = {}
    for p in d.glob("*.json") if d.exists() else []:
        with contextlib.suppress(json.JSONDecodeError, OSError):
            r = json.loads(p.read_text())
            if r["status"] in ("done", "empty"):
                out[r["unit"]] = r["updated_at"]
    return out


# ------------------------------------------------------------------------------------------ schedule


def _flow_runs(api: str, deployment_id: str, state: str = "COMPLETED") -> list[dict]:
    """Flow runs of a deployment in a state (the server schedules ~100 future runs: filter, never page)."""
    r = httpx.post(f"{api}/flow_runs/filter", json={
        "deployments": {"id": {"any_": [deployment_id]}}, "flow_runs": {"state": {"type": {"any_": [state]}}},
        "sort": "EXPECTED_START_TIME_DESC", "limit": 50}, timeout=30)
    r.raise_for_status()
    return r.json()


def test_serve_fires_a_one_minute_schedule_and_a_rerun_skips_everything(tmp_path, prefect_api, campus):
    config = campus
    work = tmp_path / "work"
    log = open(tmp_path / "serve.log", "wb")
    proc = subprocess.Popen(
        [sys.executable, "-m", "flows.cli", "serve", str(config), "--cron", "* * * * *", "--name", "every-minute",
         "--work-dir", str(work), "--set", "runner=local"],
        env=_env(PREFECT_API_URL=prefect_api), stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        def deployment():
            r = httpx.get(f"{prefect_api}/deployments/name/reprocess-campus-from-config/every-minute", timeout=10)
            return r.json() if r.status_code == 200 else None

        dep = _wait(deployment, 90, "the served deployment")
        assert dep["schedules"] and dep["schedules"][0]["schedule"]["cron"] == "* * * * *"

        def completed(scheduled: bool):
            runs = _flow_runs(prefect_api, dep["id"])
            return [r for r in runs if r["state_type"] == "COMPLETED" and r["auto_scheduled"] == scheduled]

        first = _wait(lambda: completed(True), 170, "a scheduled run to complete", period_s=2)[0]
        assert first["auto_scheduled"]
        stamps = _partition_records(work)
        assert stamps, "the scheduled run partitioned the campus"

        r = httpx.post(f"{prefect_api}/deployments/{dep['id']}/create_flow_run", json={}, timeout=30)
        r.raise_for_status()
        manual = r.json()["id"]
        _wait(lambda: any(x["id"] == manual for x in completed(False)), 120, "the triggered run to complete", 2)
        assert _partition_records(work) == stamps  # the second run skipped every tile
    finally:
        _stop(proc, signal.SIGINT)
        log.close()
    assert "Traceback" not in (tmp_path / "serve.log").read_text()


# ------------------------------------------------------------------------------------------ cluster


def test_cluster_from_the_command_line_survives_a_killed_worker(tmp_path, prefect_api, campus, clean_checksums):
    config = campus
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    env = _env(PREFECT_API_URL=prefect_api, MS3D_FAULT_PARTITION_DELAY_S="1.5",
               DASK_DISTRIBUTED__SCHEDULER__ALLOWED_FAILURES="3", PREFECT_LOGGING_LEVEL="WARNING")
    dask_bin = Path(sys.executable).parent / "dask"
    procs = [subprocess.Popen([str(dask_bin), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                               "--no-dashboard"], env=env, cwd=tmp_path, start_new_session=True,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for _ in range(2):
            procs.append(subprocess.Popen([str(dask_bin), "worker", address, "--nthreads", "1", "--no-dashboard",
                                           "--local-directory", str(tmp_path / "dask")],
                                          env=env, cwd=tmp_path, start_new_session=True,
                                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        from distributed import Client

        client = Client(address, timeout=60)
        client.wait_for_workers(2, timeout=60)
        work = tmp_path / "work"
        run = subprocess.Popen(
            [sys.executable, "-m", "flows.cli", "run", str(config), "--dask-address", address,
             "--work-dir", str(work), "--set", "cluster.tiles_per_task=1"],
            env=env, cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)

        def busy_partition_worker():
            for addr, keys in client.processing().items():
                if any("partition" in str(k) for k in keys):
                    return addr
            return None

        victim = _wait(busy_partition_worker, 240, "a worker busy with a partition task", period_s=0.2)
        pid = client.run(os.getpid, workers=[victim])[victim]
        os.kill(pid, signal.SIGKILL)  # the worker process, mid-partition; its nanny restarts it
        out, err = run.communicate(timeout=600)
        assert run.returncode == 0, err.decode()[-3000:]
        assert "tiles:" in out.decode() and err.decode().strip() == ""
        client.close()
    finally:
        for p in reversed(procs):
            _stop(p)
    assert not _temporary_files(work)
    assert _checksums(work) == clean_checksums


# ------------------------------------------------------------------------------------------ kill -9


def test_kill_9_of_a_whole_run_then_rerun_redoes_only_unfinished_units(tmp_path, campus, clean_checksums):
    config = campus
    work = tmp_path / "work"
    cmd = [sys.executable, "-m", "flows.cli", "run", str(config), "--work-dir", str(work),
           "--set", "cluster.tiles_per_task=1"]
    env = _env(MS3D_FAULT_PARTITION_DELAY_S="1.0")
    env.pop("PREFECT_API_URL", None)  # the run starts its own embedded server, as a user's would
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            start_new_session=True)
    try:
        _wait(lambda: len(_partition_records(work)) >= 3, 300, "three tiles partitioned", period_s=0.2)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)  # kill -9 of the run and everything it started
        proc.wait()
    before = _partition_records(work)
    ingest_before = {r.unit: r.updated_at for r in all_records(WorkDir(work))
                     if r.stage == "ingest" and r.status == "done"}
    assert before and ingest_before

    env.pop("MS3D_FAULT_PARTITION_DELAY_S")
    rerun = subprocess.run(cmd, env=env, capture_output=True, timeout=600)
    assert rerun.returncode == 0, rerun.stderr.decode()[-3000:]
    after = _partition_records(work)
    redone = {k: json.loads((work / "manifest.d" / "partition" / f"{k}.json").read_text())["summary"].get("redo")
              for k in before if after[k] != before[k]}
    assert not redone, f"units finished before the kill were redone: {redone}"
    assert len(after) > len(before)

    ingest_after = {r.unit: r.updated_at for r in all_records(WorkDir(work)) if r.stage == "ingest"}
    assert {k: ingest_after[k] for k in ingest_before} == ingest_before
    assert not _temporary_files(work)
    assert _checksums(work) == clean_checksums
