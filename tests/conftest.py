"""Shared fixtures: one Prefect API server per test session (never one per test), and the tiny synth campus
with its work dirs built once per run for every xdist worker."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest


def _built_once(tmp_path_factory, name: str, build) -> Path:
    """The folder ``name`` built by ``build(folder)`` once per test run, shared by every xdist worker (the first
    builds it under a file lock; the others wait and reuse it; a ``.built`` marker says it is complete). Without
    xdist it is a plain per-session folder. Never to be changed: read it, or take :func:`_own_copy`."""
    from filelock import FileLock

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, above each worker's own basetemp
    folder = root / f"shared-{name}"
    with FileLock(str(folder) + ".lock"):
        if not (folder / ".built").exists():
            if folder.exists():
                import shutil

                shutil.rmtree(folder)  # a worker that died mid-build left it half made
            folder.mkdir(parents=True)
            build(folder)
            (folder / ".built").touch()
    return folder


def _own_copy(tmp_path_factory, name: str, src: Path) -> Path:
    """A copy of ``src`` in this worker's own temp folder: built once, but changed by no other worker."""
    import shutil

    return Path(shutil.copytree(src, tmp_path_factory.mktemp(name) / src.name, symlinks=True))


@pytest.fixture(scope="session")
def prefect_api(tmp_path_factory):
    """Start one local Prefect server (SQLite in a temp dir) and point PREFECT_API_URL at it."""
    from flows.runtime import PrefectServer, prefect_env

    home = tmp_path_factory.mktemp("prefect")
    saved = dict(os.environ)
    os.environ.update(prefect_env(home))
    os.environ["PREFECT_LOGGING_LEVEL"] = "WARNING"
    server = PrefectServer(home).start()
    os.environ["PREFECT_API_URL"] = server.api_url
    yield server.api_url
    from flows.runtime import drain_prefect_services

    drain_prefect_services()
    server.stop()
    os.environ.clear()
    os.environ.update(saved)


@pytest.fixture(scope="session")
def tiny_campus(tmp_path_factory):
    """The synth 'tiny' campus (seed 1), generated once per run and read by every worker. Read-only for tests."""
    from synth.generate import generate

    return _built_once(tmp_path_factory, "tiny", lambda d: generate("tiny", seed=1, out=d / "campus")) / "campus"


@pytest.fixture(scope="session")
def tiny_merged(tiny_campus, tmp_path_factory):
    """A work dir with campus.json and tiles/*/merged.* cut from the tiny synth mesh (25 m tiles, 3 x 2),
    standing in for the merge stage's output; built once per run, each worker its own copy. Read-only for tests
    (copy it to change it)."""
    import yaml

    from storage.frame import CampusFrame
    from synth.tile_meshes import fake_merged_workdir, read_production

    def build(folder):
        cfg = yaml.safe_load((tiny_campus / "campus.yaml").read_text())
        mesh, origin = read_production(tiny_campus / "mesh")
        frame = CampusFrame(origin=origin, crs=cfg["inputs"]["crs"], vertical_datum="ellipsoidal (WGS 84), synthetic")
        fake_merged_workdir(mesh, frame, folder / "work", tile_size_m=25.0)

    return _own_copy(tmp_path_factory, "merged", _built_once(tmp_path_factory, "merged", build) / "work")


@pytest.fixture(scope="session")
def tiny_export(tiny_merged, tmp_path_factory):
    """``tiny_merged`` exported (uncompressed) into a copy of the work dir; returns (work dir, summary)."""
    import shutil

    from tasks.export import run_export

    def build(folder):
        shutil.copytree(tiny_merged, folder / "work")
        (folder / "summary.json").write_text(json.dumps(run_export(folder / "work")))

    folder = _built_once(tmp_path_factory, "export", build)
    return _own_copy(tmp_path_factory, "export", folder / "work"), json.loads((folder / "summary.json").read_text())


@pytest.fixture(scope="session")
def tiny_work(tiny_campus, tmp_path_factory):
    """The tiny synth campus processed once per run (inline, classify off), each worker its own copy:
    (config, WorkDir). Read-only for tests."""
    from flows.campus import run_campus
    from storage.workdir.layout import WorkDir
    from tasks.config import CampusConfig

    def config(work):
        return CampusConfig.from_yaml(tiny_campus / "campus.yaml", {"work_dir": str(work), "runner": "inline",
                                                                   "classify": {"enabled": False}})

    built = _built_once(tmp_path_factory, "model-tiny", lambda d: run_campus(config(d / "work"), progress=False))
    work = _own_copy(tmp_path_factory, "model-tiny", built / "work")
    return config(work), WorkDir(work)


@pytest.fixture(scope="session")
def moto_s3():
    """moto's S3 server (it speaks the S3 HTTP API) on 127.0.0.1 with an ephemeral port, one per test session;
    yields ``make_bucket(bucket, key_id, secret) -> endpoint URL``. Never bound to a public interface."""
    import boto3
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    assert host == "127.0.0.1"
    endpoint = f"http://{host}:{port}"

    def make_bucket(bucket: str, key_id: str, secret: str) -> str:
        boto3.client("s3", endpoint_url=endpoint, aws_access_key_id=key_id, aws_secret_access_key=secret,
                     region_name="us-east-1").create_bucket(Bucket=bucket)
        return endpoint

    yield make_bucket
    server.stop()
