"""Map only the units that must run: a stage's task function is first called in the flow's own process
under :func:`tasks.units.planning`, where every ``run_unit`` either returns the skipped summary of a
current unit or raises ``MustRun``; only the units that raised are then handed to task runs.

So what is skipped is decided by each stage's own fingerprints and parameters, with the rule
``run_unit`` applies (one read of each stage's records), and a no-op rerun launches no task run for a
stage that is up to date. A stage whose fingerprints depend on an earlier stage's outputs is planned
after that stage finished (the flow calls :func:`map_pending` stage by stage).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from storage.workdir.layout import WorkDir
from tasks.units import MustRun, planning

log = logging.getLogger("ms3d.flow")

__all__ = ["map_pending", "pending", "submit_pending", "unit_name"]


def unit_name(u) -> str:
    """The manifest unit of a task argument: a tile / region key, an ingest unit's ``key`` or a scanned
    file's source id (8 hex digits)."""
    if isinstance(u, dict):
        return u.get("key") or f"{u.get('source', 0):08x}"
    return str(u)


def pending(wd: WorkDir, tsk, units: list, label: str, **consts) -> tuple[list, dict[int, list[dict]]]:
    """Which of ``units`` must run as task runs of ``tsk`` (a ``flows.tasks`` task over a batch).

    Returns (the units that must run, in the given order; {index in ``units``: the task function's
    results for that up-to-date unit}). Logs "stage <label>: N units up to date" when none must run.
    """
    todo, done = [], {}
    with planning(wd):
        for i, u in enumerate(units):
            try:
                done[i] = tsk.fn([u], **consts)
            except MustRun:
                todo.append(u)
    if units and not todo:
        log.info("stage %s: %d units up to date", label, len(units))
    elif units:
        log.info("stage %s: %d of %d units to run", label, len(todo), len(units))
    return todo, done


def map_pending(wd: WorkDir, ex, tsk, units: list, label: str, batch: Callable[[list], list[list]],
                **consts) -> list[dict]:
    """The unit summaries of ``tsk`` over ``units``: the up-to-date units' from planning (no task run),
    the others' from task runs over ``batch(units that must run)``. In the order of ``units`` (by unit
    name); results that name no planned unit come last."""
    todo, done = pending(wd, tsk, units, label, **consts)
    mapped = ex.map(tsk, batch(todo), label, **consts).results() if todo else []
    return in_unit_order(units, done, mapped)


def in_unit_order(units: list, done: dict[int, list[dict]], mapped: list[dict]) -> list[dict]:
    """The results of planning (``done``, by index) and of task runs (``mapped``, by ``"unit"``) in the
    order of ``units``.

    >>> in_unit_order(["a", "b", "c"], {1: [{"unit": "b"}]}, [{"unit": "c"}, {"unit": "a"}, {"unit": "x"}])
    [{'unit': 'a'}, {'unit': 'b'}, {'unit': 'c'}, {'unit': 'x'}]
    """
    by_unit: dict[str, list[dict]] = {}
    for r in mapped:
        by_unit.setdefault(str(r.get("unit")), []).append(r)
    out = []
    for i, u in enumerate(units):
        out += done[i] if i in done else by_unit.pop(unit_name(u), [])
    return out + [r for rs in by_unit.values() for r in rs]


class _Ready:
    """The result of a campus-wide unit that was up to date, shaped like a task future."""

    def __init__(self, value):
        self.value = value

    def result(self):
        return self.value


def submit_pending(wd: WorkDir, ex, tsk, *args):
    """``tsk(*args)`` over one campus-wide unit (e.g. the registration): its result from planning when
    the unit is up to date (no task run), else a task run submitted on ``ex``. Either has ``.result()``."""
    try:
        with planning(wd):
            return _Ready(tsk.fn(*args))
    except MustRun:
        return ex.submit(tsk, *args)
