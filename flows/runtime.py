"""The embedded runtime: one local Prefect API server (SQLite in the work dir) and a Dask cluster.

Dask worker *processes* do not inherit Prefect's ephemeral in-process server: without a reachable
``PREFECT_API_URL`` each worker would start its own server and they would fight over one SQLite file.
So ``embedded_prefect`` starts exactly one server as a child process, points ``PREFECT_API_URL`` (in
``os.environ``, which the cluster's workers inherit, and in the Prefect settings context) at it, and
stops it cleanly at the end after draining the log and event workers (otherwise exit hangs ~75 s).

The database lives in ``WORKDIR/prefect/prefect.db``, so the run history survives:
``ms3d ui WORKDIR`` (``prefect server start`` with that database) shows it later.

Every server started here listens on 127.0.0.1 only (:data:`LOOPBACK`): the Prefect API (see
``flows._server``) and, in ``flows.campus.make_task_runner``, the local Dask scheduler and workers (no
dashboard). A remote cluster or API is used only when configured by address.

Stopping: :func:`stop_on_signals` turns SIGINT and SIGTERM into :class:`Stopped` (a KeyboardInterrupt,
so Prefect, Dask and asyncio unwind as on Ctrl-C): the flow's context managers close the Dask client
and cluster, release the work-dir lock and stop the embedded server; the CLI then prints
:func:`stopped_line` and exits with 128 + the signal number (130 for SIGINT, 143 for SIGTERM). A second
signal while unwinding exits at once (the OS releases the lock; the server's watchdog ends it).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

log = logging.getLogger("ms3d.runtime")

LOOPBACK = "127.0.0.1"  # the one interface every server ms3d starts listens on


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
        s.bind((LOOPBACK, 0))
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
        self.host = LOOPBACK
        self.port = port or _free_port()
        self.proc: subprocess.Popen | None = None

    @property
    def api_url(self) -> str:
        return f"http://{self.host}:{self.port}/api"

    def command(self) -> list[str]:
        """The child process's command line (``flows._server`` on ``host:port``)."""
        return [sys.executable, "-m", "flows._server", str(self.port), self.host]

    def start(self, timeout_s: float = 120) -> PrefectServer:
        """Launch the server and wait until it answers (:meth:`launch`, then :meth:`wait_healthy`)."""
        return self.launch().wait_healthy(timeout_s)

    def launch(self) -> PrefectServer:
        """Start the child process and return at once (it takes ~10 s to answer: do other work meanwhile)."""
        env = {**os.environ, **prefect_env(self.prefect_dir), "PREFECT_UI_ENABLED": "0",
               "PREFECT_LOGGING_LEVEL": "WARNING"}
        env.pop("PREFECT_API_URL", None)
        log_path = self.prefect_dir / "server.log"
        self._log = open(log_path, "ab")
        # its own session: a Ctrl-C reaches the terminal's whole process group, and the server must
        # outlive the flow run that reports its cancellation (stop() ends it; so does its watchdog)
        self.proc = subprocess.Popen(
            self.command(),
            env=env, stdout=self._log, stderr=subprocess.STDOUT, start_new_session=True,
        )
        return self

    def wait_healthy(self, timeout_s: float = 120) -> PrefectServer:
        """Wait until the launched server answers; stops it (and raises) when it does not."""
        try:
            _wait_healthy(self.api_url, self.proc, timeout_s, self.prefect_dir / "server.log")
        except BaseException:  # not healthy, or stopped (a signal) while starting: leave no server behind
            self.stop()
            raise
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


# glibc's heap settings for the Dask worker processes. Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 before it
# spawns a worker, which also freezes glibc's mmap threshold at 128 kB: every numpy array above it is mapped and
# unmapped again, each page faulted in anew. Measured on the demo's densest tile, grading took 22.8 s with it
# against 16.8 s without (sys 7.0 s, 2.3 M page faults, against 2.1 s, 0.36 M), with the same peak RSS. These
# are glibc's own dynamic defaults at their ceiling; every unit hands its freed heap back at its start
# (``tasks.units``), so a worker does not hold on to memory between units. A variable set in the
# environment wins (Dask reads it from there first).
WORKER_MALLOC_ENV = {"MALLOC_TRIM_THRESHOLD_": str(64 << 20), "MALLOC_MMAP_THRESHOLD_": str(32 << 20)}


def worker_spawn_environ() -> dict:
    """Set :data:`WORKER_MALLOC_ENV` in Dask's ``distributed.nanny.pre-spawn-environ`` (process-wide: nannies
    read it when they start their worker) and return the resulting mapping."""
    import dask

    env = {**dask.config.get("distributed.nanny.pre-spawn-environ", {}), **WORKER_MALLOC_ENV}
    dask.config.set({"distributed.nanny.pre-spawn-environ": env})
    return env


def task_durations() -> dict[str, str]:
    """Dask's first guess of each long task's duration, from the stages' declarations (``StageSpec.duration``),
    keyed by task function name (Dask's key prefix). The flow submits the quality shares and the report's renders
    beside the export's leaves while every worker is busy: guessed at Dask's 0.5 s, the leaves queued on one
    worker and were not stolen."""
    from flows import tasks

    found = [getattr(tasks, n) for n in dir(tasks)]
    return {t.fn.__name__: t.spec.duration for t in found if getattr(getattr(t, "spec", None), "duration", None)}


def scheduler_task_durations() -> dict:
    """Set :func:`task_durations` in Dask's ``distributed.scheduler.default-task-durations`` (process-wide:
    the local cluster's scheduler runs in this process) and return the resulting mapping."""
    import dask

    durations = {**dask.config.get("distributed.scheduler.default-task-durations", {}), **task_durations()}
    dask.config.set({"distributed.scheduler.default-task-durations": durations})
    return durations


def local_cluster_kwargs(n_workers: int, threads_per_worker: int, memory_limit) -> dict:
    """Keyword arguments of the local ``distributed.LocalCluster``: worker processes, scheduler and
    workers on 127.0.0.1, no dashboard, and this module as the workers' preload (:func:`dask_setup`).
    Also sets the workers' heap settings (:func:`worker_spawn_environ`) and the scheduler's first guess of
    the long tasks' durations (:func:`scheduler_task_durations`)."""
    worker_spawn_environ()
    scheduler_task_durations()
    return {"n_workers": n_workers, "threads_per_worker": threads_per_worker, "processes": True,
            "memory_limit": memory_limit, "host": LOOPBACK, "dashboard_address": None,
            "preload": [__name__]}


def dask_setup(worker) -> None:
    """Dask worker preload: ignore SIGINT. A Ctrl-C reaches every process of the terminal's group; the
    worker is stopped by its nanny when the flow closes the cluster (or exits when its nanny dies),
    instead of printing a KeyboardInterrupt traceback of its own."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def drain_prefect_services(timeout_s: float = 10) -> None:
    """Flush Prefect's background log and event workers so the process exits promptly."""
    with contextlib.suppress(Exception):
        from prefect.logging.handlers import APILogWorker

        APILogWorker.drain_all(timeout=timeout_s)
    with contextlib.suppress(Exception):
        from prefect.events.worker import EventsWorker

        EventsWorker.drain_all(timeout=timeout_s)


@contextlib.contextmanager
def embedded_prefect(prefect_dir: Path, api_url: str | None = None,
                     launched: PrefectServer | None = None) -> Iterator[str]:
    """Yield a reachable Prefect API URL: ``api_url`` / an inherited PREFECT_API_URL, or a new
    local server with its database in ``prefect_dir`` (stopped on exit). launched: that server, already
    launched (:meth:`PrefectServer.launch`) by a caller that had other work to do while it starts."""
    api_url = None if launched is not None else api_url or os.environ.get("PREFECT_API_URL")
    server = None
    saved = {k: os.environ.get(k) for k in ("PREFECT_API_URL", "PREFECT_HOME", "PREFECT_API_DATABASE_CONNECTION_URL")}
    if launched is not None:
        server = launched.wait_healthy()
        api_url = server.api_url
        os.environ.update(prefect_env(Path(prefect_dir)))
    elif not api_url:
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


# ------------------------------------------------------------------------------------------ stopping


class Stopped(KeyboardInterrupt):
    """SIGINT or SIGTERM asked ms3d to stop (``signum``); ``exit_code`` is 128 + signum."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def signal_name(self) -> str:
        return signal.Signals(self.signum).name

    @property
    def exit_code(self) -> int:
        return 128 + self.signum


_stopping: list[int] = []  # signals received since stop_on_signals was entered


def _on_stop_signal(signum: int, _frame) -> None:
    _stopping.append(signum)
    if len(_stopping) > 1:  # asked again while unwinding: stop now
        os._exit(128 + signum)
    raise Stopped(signum)


@contextlib.contextmanager
def stop_on_signals(signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[None]:
    """Within the block, ``signals`` raise :class:`Stopped` in the main thread (the first one; a
    second one exits the process at once). Prefect swaps its own SIGTERM bridge in while a flow runs
    and, on SIGTERM, re-sends the signal to the handler it replaced: this one. Main thread only."""
    saved = {s: signal.signal(s, _on_stop_signal) for s in signals}
    _stopping.clear()
    try:
        yield
    finally:
        for s, h in saved.items():
            signal.signal(s, h)


def stop_requested() -> int | None:
    """The first stop signal received inside :func:`stop_on_signals`, or None."""
    return _stopping[0] if _stopping else None


def units_done(work_dir: Path) -> int:
    """How many (stage, unit) records of ``work_dir`` say done or empty: what the next run skips."""
    from storage.workdir.layout import WorkDir
    from storage.workdir.manifest import all_records

    with contextlib.suppress(Exception):  # a stop message must never fail
        return sum(r.status in ("done", "empty") for r in all_records(WorkDir(work_dir)))
    return 0


def stopped_line(signum: int, work_dir: Path) -> str:
    """The one line ms3d prints when a signal stopped it."""
    name = signal.Signals(signum).name
    return f"ms3d: stopped by {name}; {units_done(work_dir)} units done, the next run resumes"
