"""The no-shared-disk cluster: moto's S3 server on 127.0.0.1, the session's Prefect server, a ``dask
scheduler`` and two ``dask worker`` processes, each in its own empty cwd with its own cache, sharing
nothing but the S3 endpoint; the second worker runs two tasks at a time (two threads). The hand-made campus runs with inputs and work dir on S3 (``ms3d run CONFIG
--work-dir s3://... --dask-address ...``); one worker is killed with SIGKILL mid-run, then the whole run;
a rerun completes, and its outputs equal a local run's by content."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from synth.handmade import build_campus

pytestmark = [pytest.mark.slow, pytest.mark.timeout(600)]

REPO = Path(__file__).resolve().parents[2]
BUCKET = "ms3d-cluster-test"
KEY_ID = "AKIAMS3DCLUSTERKEY01"
SECRET = "ms3d-cluster-secret-DO-NOT-LOG-2b7e"
OVERRIDES = {"classify.enabled": "false", "report.enabled": "false", "cluster.tiles_per_task": "1"}
LEASE_TTL_S = 6


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def s3_env(tmp_path, monkeypatch):
    """moto's server on 127.0.0.1 with a bucket; the AWS environment for this test and its children."""
    import boto3
    from moto.server import ThreadedMotoServer

    from storage.inputs import remote as remote_inputs
    from storage.objstore import mirror as remote_workdir

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    assert host == "127.0.0.1"
    endpoint = f"http://{host}:{port}"
    env = {"AWS_ENDPOINT_URL": endpoint, "AWS_ACCESS_KEY_ID": KEY_ID, "AWS_SECRET_ACCESS_KEY": SECRET,
           "AWS_DEFAULT_REGION": "us-east-1", "MS3D_CACHE": str(tmp_path / "test-cache")}
    for k in ("AWS_PROFILE", "AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setattr(remote_inputs, "_STORES", {})
    monkeypatch.setattr(remote_workdir, "_MIRRORS", {})
    boto3.client("s3", endpoint_url=endpoint, region_name="us-east-1").create_bucket(Bucket=BUCKET)
    yield env
    server.stop()


def _child_env(cache: Path) -> dict:
    env = {**os.environ, "MS3D_CACHE": str(cache), "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1",
           "MS3D_LEASE_TTL_S": str(LEASE_TTL_S), "PREFECT_LOGGING_LEVEL": "WARNING"}
    return env


@pytest.fixture
def dask_cluster(tmp_path, s3_env, prefect_api):
    """A scheduler and two workers (no nanny: SIGKILL ends a worker for good), each in its own empty cwd
    with its own cache; worker0 has one thread, worker1 two. Yields (address, {name: Popen})."""
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    procs = {}
    logs = []

    def start(name: str, args: list[str]) -> subprocess.Popen:
        cwd = tmp_path / name
        cwd.mkdir()
        log = open(tmp_path / f"{name}.log", "wb")  # noqa: SIM115 - closed at teardown
        logs.append(log)
        return subprocess.Popen([sys.executable, "-m", "dask", *args], cwd=cwd, env=_child_env(cwd / "cache"),
                                stdout=log, stderr=subprocess.STDOUT)

    procs["scheduler"] = start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", str(port),
                                             "--no-dashboard", "--no-show"])
    for i in range(2):
        # worker1 runs two tasks at a time (two threads, one process): the stores must still equal the inline run's
        procs[f"worker{i}"] = start(f"worker{i}", ["worker", address, "--host", "127.0.0.1", "--nthreads", str(1 + i),
                                                  "--no-nanny", "--no-dashboard", "--name", f"w{i}"])
    from distributed import Client

    with Client(address, timeout=60) as c:
        c.wait_for_workers(2, timeout=120)
    try:
        yield address, procs
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
            p.wait()
        for log in logs:
            log.close()


def _run_cmd(config: Path, work_url: str, address: str) -> list[str]:
    cmd = [sys.executable, "-m", "flows.cli", "run", str(config), "--work-dir", work_url, "--dask-address", address]
    for k, v in OVERRIDES.items():
        cmd += ["--set", f"{k}={v}"]
    return cmd


def _n_records(store) -> int:
    return len(store.list("records/sync"))


def test_no_shared_disk_cluster_survives_a_killed_worker_and_a_killed_run(tmp_path, s3_env, dask_cluster):
    import yaml

    from flows.campus import InlineExecutor, run_campus
    from flows.remote import mirror_for
    from storage.objstore.store import open_store
    from tasks.config import CampusConfig

    from .test_s3_workdir import tables_by_content, upload

    address, procs = dask_cluster
    prefix = f"s3://{BUCKET}/{uuid.uuid4().hex[:10]}"
    campus = build_campus(tmp_path / "campus")
    upload(campus.parent, prefix + "/campus")
    doc = yaml.safe_load(campus.read_text())
    doc["inputs"].update(mesh=[prefix + "/campus/mesh"], points=[prefix + "/campus/mls"])
    remote_yaml = tmp_path / "remote.yaml"
    remote_yaml.write_text(yaml.safe_dump(doc))

    over = {k: (v == "true") if v in ("true", "false") else int(v) for k, v in OVERRIDES.items()}
    run_campus(CampusConfig.from_yaml(campus, {**over, "work_dir": str(tmp_path / "local"), "runner": "inline"}),
               executor=InlineExecutor())

    work = prefix + "/work"
    store = open_store(work)
    driver_cwd = tmp_path / "driver"
    driver_cwd.mkdir()
    log = open(tmp_path / "driver.log", "wb")  # noqa: SIM115
    driver = subprocess.Popen(_run_cmd(remote_yaml, work, address), cwd=driver_cwd,
                              env=_child_env(driver_cwd / "cache"), stdout=log, stderr=subprocess.STDOUT)
    try:
        t0 = time.time()
        while _n_records(store) < 4 and driver.poll() is None and time.time() - t0 < 240:
            time.sleep(0.5)
        procs["worker0"].send_signal(signal.SIGKILL)  # a worker dies mid-run
        seen = _n_records(store)
        while _n_records(store) < seen + 3 and driver.poll() is None and time.time() - t0 < 300:
            time.sleep(0.5)
        killed_mid_run = driver.poll() is None
        driver.send_signal(signal.SIGKILL)  # then the whole run
        driver.wait()
    finally:
        log.close()
    assert killed_mid_run, (tmp_path / "driver.log").read_text()[-2000:]
    time.sleep(LEASE_TTL_S + 1)  # the killed run's lease expires: it cannot hold the work dir forever
    rerun = subprocess.run(_run_cmd(remote_yaml, work, address), check=False, cwd=driver_cwd,
                           env=_child_env(driver_cwd / "cache2"),
                           capture_output=True, text=True, timeout=400)
    (tmp_path / "rerun.log").write_text(rerun.stdout + rerun.stderr)
    assert rerun.returncode == 0, (rerun.stdout + rerun.stderr)[-3000:]
    resumed = [int(n) for n in re.findall(r"(\d+) unchanged \(skipped\)", rerun.stdout)]
    assert sum(resumed) > 0, rerun.stdout  # what the killed run committed is not done again
    assert SECRET not in rerun.stdout + rerun.stderr and KEY_ID not in rerun.stdout + rerun.stderr

    mirror = mirror_for(work)  # this process: a fresh mirror of what the bucket records
    mirror.pull()
    assert tables_by_content(mirror.root) == tables_by_content(tmp_path / "local")
    assert list((mirror.root / "manifest.d" / "partition").glob("*.json"))
    for name in ("worker0", "worker1", "driver"):  # no disk shared: each cwd holds only its own cache
        assert {p.name for p in (tmp_path / name).iterdir()} <= {"cache", "cache2"}
