"""Shared fixtures: one Prefect API server for the whole test session (never one per worker or test)."""

from __future__ import annotations

import os

import pytest


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
    """The synth 'tiny' campus (seed 1), generated once per test session. Read-only for tests."""
    from synth.generate import generate

    return generate("tiny", seed=1, out=tmp_path_factory.mktemp("tiny") / "campus")
