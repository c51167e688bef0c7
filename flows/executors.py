"""Where the campus flow runs its tasks: as Prefect task runs on the flow's task runner (Dask workers), or
inline in this process without Prefect (tests, debugging). Both give the flow the same two calls."""

from __future__ import annotations

import contextlib
import logging

import dask
from prefect import unmapped

from flows.progress import wait_all

log = logging.getLogger("ms3d.flow")


class PrefectExecutor:
    """Runs tasks as Prefect task runs on the flow's task runner (Dask workers)."""

    def __init__(self, progress: bool):
        self.progress = progress
        self.task_runs = 0  # submitted so far (each should be one task run on the API)

    def map(self, tsk, batches: list, label: str, **consts) -> _Mapped | _Done:
        if not batches:  # nothing to run (the planner skipped every unit): no task run, no progress bar
            return _Done([])
        with _priority(tsk):
            futs = tsk.map(batches, **{k: unmapped(v) for k, v in consts.items()})
        self.task_runs += len(futs)
        return _Mapped(batches, futs, label, self.progress)

    def submit(self, tsk, *args):
        self.task_runs += 1
        with _priority(tsk):
            return tsk.submit(*args)

    def recycle_workers(self, over_mb: float) -> dict:
        """Restart the flow's Dask workers (between stages, nothing running) when one of them holds more than
        ``over_mb`` of RSS: what earlier stages left (torch, Arrow and glibc pools) then no longer counts
        against a later stage's peak. Returns {"restarted": number of workers, "largest_mb": RSS before}."""
        client = _flow_client()
        if client is None:
            return {"restarted": 0, "largest_mb": 0.0}
        try:
            rss = client.run(_rss_mb)
        except Exception:  # noqa: BLE001 - not a Dask runner, or no cluster to ask: nothing to recycle
            return {"restarted": 0, "largest_mb": 0.0}
        largest = max(rss.values(), default=0.0)
        if largest <= over_mb:
            return {"restarted": 0, "largest_mb": largest}
        try:
            client.restart(wait_for_workers=True)
        except Exception as e:  # noqa: BLE001 - the run goes on with the workers it has; one line says why
            log.warning("could not restart the workers before merge: %s", f"{type(e).__name__}: {e}".splitlines()[0])
            return {"restarted": 0, "largest_mb": largest}
        return {"restarted": len(rss), "largest_mb": largest}


    def slots(self) -> int:
        """Task slots (threads) of the Dask workers connected now: what an external cluster really has, not
        what ``cluster.n_workers`` says; 0 when unknown (no cluster started yet, not a Dask runner)."""
        client = _flow_client()
        if client is None:
            return 0
        try:
            return int(sum(client.nthreads().values()))
        except Exception:  # noqa: BLE001 - no scheduler to ask: the caller falls back to the config
            return 0


def _flow_client():
    """The Dask client of the running flow's task runner; None until a task ran (a no-op rerun starts no
    cluster) or outside a Dask runner."""
    from prefect.context import FlowRunContext

    runner = getattr(FlowRunContext.get(), "task_runner", None)
    return getattr(runner, "_client", None)


def _priority(tsk):
    """The Dask priority its stage declares (``tsk.spec.priority``) around a submission; none when 0."""
    priority = getattr(getattr(tsk, "spec", None), "priority", 0)
    return dask.annotate(priority=priority) if priority else contextlib.nullcontext()


def _rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


class _Mapped:
    def __init__(self, batches, futs, label, progress):
        self.batches, self.futs, self.label, self.progress = batches, futs, label, progress

    def results(self) -> list[dict]:
        return _collect(self.batches, wait_all(self.futs, self.label, self.progress), self.label)


class InlineExecutor:
    """Runs the task functions in this process, one after the other, without Prefect (tests, debugging)."""

    def map(self, tsk, batches: list, label: str, **consts) -> _Done:
        return _Done([r for b in batches for r in tsk.fn(b, **consts)])

    def submit(self, tsk, *args) -> _Done:
        return _Done(tsk.fn(*args))

    def recycle_workers(self, over_mb: float) -> dict:
        return {"restarted": 0, "largest_mb": 0.0}  # no worker processes

    def slots(self) -> int:
        return 0  # no cluster: the config's worker count decides


class _Done:
    def __init__(self, value):
        self.value = value

    def results(self):
        return self.value

    def result(self):
        return self.value


def _collect(batches: list[list], states: list, what: str) -> list[dict]:
    """Unit summaries of mapped tasks; a task that crashed (a bug, a killed worker beyond Dask's
    retries) fails each of its units with its one-line error."""
    out = []
    for batch, st in zip(batches, states):
        if st.is_completed():
            out += st.result()
        else:
            err = _state_error(st)
            out += [{"unit": _unit_name(u), "status": "failed", "error": f"{what} task failed: {err}",
                     "skipped": False} for u in batch]
    return out


def _unit_name(u) -> str:
    if isinstance(u, dict):
        return u.get("key") or f"{u.get('source', 0):08x}"
    return str(u)


def _state_error(state) -> str:
    try:
        state.result()
    except Exception as e:
        return f"{type(e).__name__}: {e}".splitlines()[0]
    return state.message or "failed"
