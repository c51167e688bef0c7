"""A service that stops when told and listens on 127.0.0.1 only.

The end-to-end test serves the hand-made campus (classify off, one Dask worker), triggers a run through
the embedded Prefect API, sends SIGTERM once units are recorded, and checks: exit within a bound with
code 143 and one line, no traceback, the work-dir lock free, no process left; then a rerun skips what
was recorded and completes.
"""

from __future__ import annotations

import fcntl
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from flows.runtime import LOOPBACK, PrefectServer, Stopped, local_cluster_kwargs, stop_on_signals

SETS = ["--set", "classify.enabled=false", "--set", "cluster.n_workers=1"]
LOOPBACKS = {"127.0.0.1", "::1"}


def test_local_servers_bind_loopback(tmp_path):
    """The embedded Prefect server and the local Dask cluster are built on 127.0.0.1, no dashboard."""
    server = PrefectServer(tmp_path)
    assert server.host == LOOPBACK == "127.0.0.1"
    assert server.command()[-1] == "127.0.0.1" and server.api_url.startswith("http://127.0.0.1:")
    kw = local_cluster_kwargs(2, 1, "1GB")
    assert kw["host"] == "127.0.0.1" and kw["dashboard_address"] is None
    from distributed import LocalCluster

    with LocalCluster(**{**kw, "n_workers": 0}) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        assert cluster.dashboard_link in ("", None) or "127.0.0.1" in cluster.dashboard_link


def test_stop_on_signals_raises_stopped_and_restores():
    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(Stopped) as e, stop_on_signals():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler interrupts this
    assert (e.value.signum, e.value.exit_code, e.value.signal_name) == (signal.SIGTERM, 143, "SIGTERM")
    assert isinstance(e.value, KeyboardInterrupt) and Stopped(signal.SIGINT).exit_code == 130
    assert signal.getsignal(signal.SIGTERM) is before


_SPAWN_THEN_CTRL_C = """
import multiprocessing, os, signal, sys, time
from flows.serve import children_ignore_sigint

def child():
    print("child SIGINT", signal.getsignal(signal.SIGINT) == signal.SIG_IGN, flush=True)
    time.sleep(2)  # a Ctrl-C lands here, as it did in a flow run still importing its modules
    print("child done", flush=True)

if __name__ == "__main__":
    signal.signal(signal.SIGINT, lambda *_: print("parent SIGINT", flush=True))
    with children_ignore_sigint() if sys.argv[1] == "wrapped" else open(os.devnull):
        p = multiprocessing.get_context("spawn").Process(target=child)
        p.start()
    time.sleep(1)
    os.killpg(0, signal.SIGINT)  # what Ctrl-C does: the whole group
    p.join()
    print("exit", p.exitcode, flush=True)
"""


@pytest.mark.parametrize("mode", ["wrapped", "bare"])
def test_a_ctrl_c_spares_the_flow_run_process_serve_spawns(tmp_path, mode):
    """A Ctrl-C while a scheduled flow run's process was still importing printed its KeyboardInterrupt
    traceback (multiprocessing's bootstrap). Processes spawned under ``children_ignore_sigint`` start with
    SIGINT ignored; the bare control shows the test can see the traceback."""
    script = tmp_path / "spawn_then_ctrl_c.py"
    script.write_text(_SPAWN_THEN_CTRL_C)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[2]), os.environ.get("PYTHONPATH", "")])}
    r = subprocess.run([sys.executable, str(script), mode], capture_output=True, text=True, timeout=60, env=env,
                       start_new_session=True, check=False)
    assert "parent SIGINT" in r.stdout, (r.stdout, r.stderr)  # the serving process still gets its Ctrl-C
    if mode == "wrapped":
        assert "child SIGINT True" in r.stdout and "child done" in r.stdout and "exit 0" in r.stdout, r.stdout
        assert "Traceback" not in r.stderr, r.stderr
    else:
        assert "KeyboardInterrupt" in r.stderr and "child done" not in r.stdout, (r.stdout, r.stderr)


def _records(work: Path) -> list[Path]:
    return sorted((work / "manifest.d").glob("*/*.json"))


def _wait(cond, timeout_s: float, what: str, proc: subprocess.Popen):
    t0 = time.monotonic()
    while not cond():
        if proc.poll() is not None:
            pytest.fail(f"ms3d exited ({proc.returncode}) before {what}")
        if time.monotonic() - t0 > timeout_s:
            proc.kill()
            pytest.fail(f"no {what} within {timeout_s} s")
        time.sleep(0.2)


def _listening(procs: list[psutil.Process]) -> set[tuple[str, int]]:
    out = set()
    for p in procs:
        try:
            out |= {(c.laddr.ip, c.laddr.port) for c in p.net_connections(kind="inet")
                    if c.status == psutil.CONN_LISTEN}
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return out


@pytest.mark.slow
def test_serve_stops_on_sigterm_mid_run_and_resumes(tmp_path):
    from synth.handmade import build_campus

    config = build_campus(tmp_path / "campus")
    work = tmp_path / "work"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("PREFECT_API_URL", None)  # serve starts its own embedded server in the work dir
    out_path = tmp_path / "serve.out"
    err_path = tmp_path / "serve.err"
    with open(out_path, "w") as out_file, open(err_path, "w") as err_file:  # files: a pipe could fill and block
        proc = subprocess.Popen(
            [sys.executable, "-m", "flows.cli", "serve", str(config), "--work-dir", str(work), "--cron", "0 2 1 1 *",
             *SETS], stdout=out_file, stderr=err_file, env=env)
    try:
        took, tree = _serve_then_sigterm(proc, out_path, work, env)
    finally:
        if proc.poll() is None:
            proc.kill()
    err, out = err_path.read_text(), out_path.read_text()
    assert proc.returncode == 143, (proc.returncode, err)
    assert "Traceback" not in err + out and "Error" not in err, err
    assert re.search(r"^ms3d: stopped by SIGTERM; \d+ units done, the next run resumes$", err, re.MULTILINE), err
    with open(work / ".lock", "a+") as f:  # free: the cancelled flow run released it
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    _, alive = psutil.wait_procs(tree[1:], timeout=15)
    assert not alive, alive
    print(f"SIGTERM to exit: {took:.1f} s")

    done_scans = [p for p in _records(work) if p.parent.name == "scan"]
    assert done_scans  # the scan stage runs first
    rerun = subprocess.run([sys.executable, "-m", "flows.cli", "run", str(config), "--work-dir", str(work), *SETS,
                            "--set", "runner=inline"], capture_output=True, text=True, env=env, timeout=120, check=False)
    assert rerun.returncode == 0, rerun.stderr
    assert (work / "output" / "tileset.json").exists()
    assert re.search(rf"^scan: \d+ run, {len(done_scans)} unchanged \(skipped\)", rerun.stdout, re.MULTILINE), \
        rerun.stdout


def _serve_then_sigterm(proc: subprocess.Popen, out_path: Path, work: Path, env: dict):
    """Trigger a run of the served deployment, check what listens, SIGTERM once a unit is recorded.
    Returns (seconds from the signal to the exit, the process tree as it was)."""
    _wait(lambda: "serving" in out_path.read_text(), 60, "serving line", proc)
    url = re.search(r" on (http\S+);", out_path.read_text()).group(1)
    trigger = ("from prefect.deployments import run_deployment; "
               "run_deployment('reprocess-campus-from-config/handmade', timeout=0)")
    subprocess.run([sys.executable, "-c", trigger], env={**env, "PREFECT_API_URL": url}, check=True, timeout=60)
    _wait(lambda: len(_records(work)) >= 1, 90, "unit recorded", proc)

    tree = [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
    listening = _listening(tree)
    assert len(listening) >= 2, listening  # at least the Prefect API and the Dask scheduler
    assert {ip for ip, _ in listening} <= LOOPBACKS, listening

    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        pytest.fail("ms3d serve still alive 30 s after SIGTERM")
    return time.monotonic() - t0, tree


@pytest.mark.slow
def test_run_stops_on_sigterm_mid_run(tmp_path):
    """``ms3d run`` (embedded Prefect, Dask): SIGTERM once a unit is recorded; Prefect's SIGTERM bridge
    hands the signal back to ms3d's handler, the flow unwinds, one line, exit 143, nothing left."""
    from synth.handmade import build_campus

    config = build_campus(tmp_path / "campus")
    work = tmp_path / "work"
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    env.pop("PREFECT_API_URL", None)
    err_path = tmp_path / "run.err"
    with open(err_path, "w") as err_file:
        proc = subprocess.Popen([sys.executable, "-m", "flows.cli", "run", str(config), "--work-dir", str(work),
                                 *SETS], stdout=err_file, stderr=subprocess.STDOUT, env=env)
    try:
        _wait(lambda: len(_records(work)) >= 1, 90, "unit recorded", proc)
        tree = [psutil.Process(proc.pid), *psutil.Process(proc.pid).children(recursive=True)]
        proc.send_signal(signal.SIGTERM)
        rc = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    out = err_path.read_text()
    assert rc == 143 and "Traceback" not in out, out
    assert re.search(r"^ms3d: stopped by SIGTERM; [1-9]\d* units done, the next run resumes$", out, re.MULTILINE), out
    with open(work / ".lock", "a+") as f:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    _, alive = psutil.wait_procs(tree[1:], timeout=15)
    assert not alive, alive


class _FakeRunner:
    """A Prefect Runner stand-in: ``start`` waits forever (still starting) or returns at once."""

    def __init__(self, returns: bool):
        self.returns, self.started, self.stopped = returns, False, False

    async def start(self):
        import asyncio

        if not self.returns:
            await asyncio.Event().wait()

    async def astop(self):
        self.stopped = True


def test_a_signal_while_the_runner_starts_cancels_the_start_and_a_runner_ending_alone_is_no_signal():
    import asyncio
    import os
    import signal as sig

    from flows.serve import serve_until_signalled

    async def signalled():
        asyncio.get_running_loop().call_later(0.2, os.kill, os.getpid(), sig.SIGTERM)
        return await asyncio.wait_for(serve_until_signalled(_FakeRunner(returns=False)), 10)

    assert asyncio.run(signalled()) == sig.SIGTERM
    assert asyncio.run(serve_until_signalled(_FakeRunner(returns=True))) == 0
