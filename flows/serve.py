"""``ms3d serve``: scheduled campus reprocessing as a served Prefect deployment.

``flow.serve`` registers a deployment of :func:`flows.campus.reprocess_from_config` with a cron schedule
on the Prefect API (the one configured, or one embedded server keeping its database in the work dir)
and runs each scheduled or triggered flow run in a subprocess until stopped (Ctrl-C / SIGTERM). Each run
resumes: units done and unchanged are skipped. ``deploy/prefect.yaml`` holds the same deployment for a
work pool on a shared server.

Stopping: the Prefect runner is driven here rather than by ``flow.serve``, whose SIGTERM handler exits
from inside the event loop (tracebacks, and a flow run left running). SIGINT and SIGTERM set an event;
the runner then cancels the flow run in progress (Prefect's control channel, then SIGTERM to its
process, which unwinds: Dask client and cluster closed, work-dir lock released), stops polling, and the
embedded server stops. ``serve_campus`` returns 128 + the signal number. A Ctrl-C reaches the terminal's
whole process group, the flow-run process too: that process starts with SIGINT ignored
(:func:`children_ignore_sigint`), so one still importing does not die with a KeyboardInterrupt traceback;
it is stopped by the runner instead.
"""

from __future__ import annotations

import asyncio
import atexit
import contextlib
import multiprocessing
import os
import shlex
import shutil
import signal
import sys
import tempfile
from pathlib import Path

from storage.errors import InputError
from storage.workdir.layout import WorkDir
from tasks.config import CampusConfig


def check_cron(cron: str) -> None:
    try:
        from croniter import croniter

        ok = croniter.is_valid(cron)
    except ImportError:  # prefect depends on croniter; be lenient if that ever changes
        ok = len(cron.split()) in (5, 6)
    if not ok:
        raise InputError(None, f"--cron {cron!r} is not a cron expression (e.g. '0 2 * * *' for 02:00 every day)")


def serve_campus(config_path: Path, cfg: CampusConfig, cron: str, name: str | None = None,
                 overrides: dict | None = None) -> int:
    """Serve the campus deployment until SIGINT or SIGTERM. Returns the exit code (130 / 143)."""
    from prefect.runner import Runner

    from flows.campus import reprocess_from_config
    from flows.runtime import embedded_prefect, stopped_line
    from storage.workdir.housekeeping import check_work_dir_writable

    check_cron(cron)
    wd = WorkDir(cfg.work_dir)
    check_work_dir_writable(wd)
    name = name or cfg.name
    params = {"config_path": str(Path(config_path).absolute()), "overrides": overrides or {}}
    with embedded_prefect(wd.prefect_dir, cfg.cluster.prefect_api_url) as url:
        runner = Runner(name=name, pause_on_shutdown=True)
        runner.add_flow(reprocess_from_config, name=name, cron=cron, parameters=params)
        print(f"serving deployment 'reprocess-campus-from-config/{name}' (cron '{cron}', UTC) on {url}; "
              "Ctrl-C stops", flush=True)
        with children_ignore_sigint():
            signum = asyncio.run(serve_until_signalled(runner))
    if signum == 0:  # the runner ended by itself (no signal)
        print("ms3d: the Prefect runner stopped on its own; see the log above", file=sys.stderr, flush=True)
        return 1
    print(stopped_line(signum, wd.root), file=sys.stderr, flush=True)
    return 128 + signum


@contextlib.contextmanager
def children_ignore_sigint():
    """Within the block, Python processes started by ``multiprocessing``'s spawn (Prefect's runner starts
    each flow run so) begin with SIGINT ignored, from their first instruction: they run through a
    ``/bin/sh`` wrapper that ignores SIGINT and execs this interpreter (an ignored signal stays ignored
    across exec, and Python then installs no KeyboardInterrupt handler). Code may still install its own
    SIGINT handler later. POSIX only; elsewhere a no-op."""
    if os.name != "posix":
        yield
        return
    from multiprocessing import spawn

    # the wrapper outlives the block: a child spawned just before it ends still has to open it (the kernel
    # hands the script to /bin/sh by path), so it is removed when this process exits
    tmp = tempfile.mkdtemp(prefix="ms3d-serve-")
    atexit.register(shutil.rmtree, tmp, True)
    wrapper = Path(tmp) / "python"
    wrapper.write_text(f"#!/bin/sh\ntrap '' INT\nexec {shlex.quote(sys.executable)} \"$@\"\n")
    wrapper.chmod(0o755)
    saved = spawn.get_executable()
    multiprocessing.set_executable(str(wrapper))
    try:
        yield
    finally:
        multiprocessing.set_executable(saved)


async def serve_until_signalled(runner, signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> int:
    """Run a Prefect ``runner`` until one of ``signals``; cancel its flow runs and stop it. Returns the
    signal number, or 0 when the runner ended without one. Main thread only (signal handlers). A signal
    that comes while the runner is still starting cancels the start."""
    loop = asyncio.get_running_loop()
    got: asyncio.Future[int] = loop.create_future()

    def on_signal(signum: int) -> None:
        if not got.done():
            got.set_result(signum)

    # Runner.start installs its own SIGTERM handler (sys.exit inside the loop): replace it with ours
    saved = {s: signal.getsignal(s) for s in signals}
    runner.handle_sigterm = lambda *_: loop.call_soon_threadsafe(on_signal, signal.SIGTERM)
    serving = asyncio.create_task(runner.start())
    await asyncio.sleep(0)  # let start() install its handler before ours replace it
    for s in signals:
        loop.add_signal_handler(s, on_signal, s)
    try:
        await asyncio.wait([got, serving], return_when=asyncio.FIRST_COMPLETED)
        if runner.started:
            await runner.astop()  # cancels the flow runs in progress and stops polling
        elif not serving.done():
            serving.cancel()  # still starting: nothing to stop yet
        with contextlib.suppress(asyncio.CancelledError):
            await serving
    finally:
        for s in signals:
            loop.remove_signal_handler(s)
            signal.signal(s, saved[s])
    return got.result() if got.done() else 0
