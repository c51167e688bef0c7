"""The embedded runtime: one local Prefect API server (SQLite in the work dir) and a Dask cluster.

Dask worker *processes* do not inherit Prefect's ephemeral in-process server: without a reachable
``PREFECT_API_URL`` each worker would start its own server and they would fight over one SQLite file.
So ``embedded_prefect`` starts exactly one server as a child process, points ``PREFECT_API_URL`` (in
``os.environ``, which the cluster's workers inherit, and in the Prefect settings context) at it, and
stops it cleanly at the end after draining the log and event workers (otherwise exit hangs ~75 s).

The database lives in ``WORKDIR/prefect/prefect.db``, so the run history survives:
``ms3d ui WORKDIR`` (``prefect server start`` with that database) shows it later.
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger("ms3d.runtime")


def prefect_env(prefect_dir: Path) -> dict[str, str]:
    """Environment for a Prefect server/client keeping its state in ``prefect_dir``."""
    prefect_dir.mkdir(parents=True, exist_ok=True)
    return {
        "PREFECT_HOME": str(prefect_dir),
        "PREFECT_API_DATABASE_CONNECTION_URL": f"sqlite+aiosqlite:///{prefect_dir / 'prefect.db'}",
        "PREFECT_SERVER_ANALYTICS_ENABLED": "false",  # the embedded server is private: no usage banner
        "PREFECT_SERVER_LOGGING_LEVEL": "WARNING",
        "PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS": "120",
    }


def _free_port() -> int:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_healthy(url: str, proc: subprocess.Popen, timeout_s: float, log_path: Path) -> None:
    import httpx

    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if proc.poll() is not None:
            tail = log_path.read_text()[-2000:] if log_path.exists() else ""
            raise RuntimeError(f"the embedded Prefect server exited with code {proc.returncode}:\n{tail}")
        with contextlib.suppress(httpx.HTTPError):
            if httpx.get(f"{url}/health", timeout=2).status_code == 200:
                return
        time.sleep(0.2)
    raise RuntimeError(f"the embedded Prefect server did not answer at {url} within {timeout_s:.0f} s")


class PrefectServer:
    """A Prefect API server running as a child process (uvicorn, SQLite)."""

    def __init__(self, prefect_dir: Path, port: int | None = None):
        self.prefect_dir = Path(prefect_dir)
        self.port = port or _free_port()
        self.proc: subprocess.Popen | None = None

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.port}/api"

    def start(self, timeout_s: float = 120) -> PrefectServer:
        env = {**os.environ, **prefect_env(self.prefect_dir), "PREFECT_UI_ENABLED": "0",
               "PREFECT_LOGGING_LEVEL": "WARNING"}
        env.pop("PREFECT_API_URL", None)
        log_path = self.prefect_dir / "server.log"
        self._log = open(log_path, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "flows._server", str(self.port)],
            env=env, stdout=self._log, stderr=subprocess.STDOUT,
        )
        _wait_healthy(self.api_url, self.proc, timeout_s, log_path)
        return self

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc = None
            self._log.close()


def drain_prefect_services(timeout_s: float = 10) -> None:
    """Flush Prefect's background log and event workers so the process exits promptly."""
    with contextlib.suppress(Exception):
        from prefect.logging.handlers import APILogWorker

        APILogWorker.drain_all(timeout=timeout_s)
    with contextlib.suppress(Exception):
        from prefect.events.worker import EventsWorker

        EventsWorker.drain_all(timeout=timeout_s)


@contextlib.contextmanager
def embedded_prefect(prefect_dir: Path, api_url: str | None = None) -> Iterator[str]:
    """Yield a reachable Prefect API URL: ``api_url`` / an inherited PREFECT_API_URL, or a new
    local server with its database in ``prefect_dir`` (stopped on exit)."""
    api_url = api_url or os.environ.get("PREFECT_API_URL")
    server = None
    saved = {k: os.environ.get(k) for k in ("PREFECT_API_URL", "PREFECT_HOME", "PREFECT_API_DATABASE_CONNECTION_URL")}
    if not api_url:
        server = PrefectServer(prefect_dir).start()
        api_url = server.api_url
        os.environ.update(prefect_env(Path(prefect_dir)))
    os.environ["PREFECT_API_URL"] = api_url
    from prefect.settings import PREFECT_API_URL, temporary_settings

    try:
        with temporary_settings(updates={PREFECT_API_URL: api_url}):
            try:
                yield api_url
            finally:
                drain_prefect_services()  # also after a failed run: else "Error logging to API" at exit
    finally:
        if server is not None:
            server.stop()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
