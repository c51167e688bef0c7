"""The one sequence every stage repeats for a unit of work: fingerprint -> skip -> run -> record.

A unit (an input file, an ingest range, a tile, a region) is skipped when its manifest record says
done (or empty) with the same input fingerprint and the same parameter hash, and its outputs exist.
The parameter hash includes the stage's version (:data:`STAGE_VERSIONS`), bumped whenever a stage's
output changes for the same inputs, so a new ms3d never reuses stale outputs of an old one.

Failures are part of the result, not exceptions: a bad input (``InputError``) or a work dir that
cannot be written (``OSError``: full disk, read-only) is recorded as ``failed`` with one clear line and
returned, so one bad unit never stops its batch and the user sees the error once, not as a traceback.
Anything else is a bug and propagates.
"""

from __future__ import annotations

import contextlib
import errno
import time
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from dataclasses import dataclass, field

from storage.errors import EmptyTileError, InputError
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import (
    ManifestRecord,
    params_hash,
    read_record,
    read_stage_records,
    record_is_current,
    redo_reason,
    write_record,
)

STAGE_VERSIONS = {
    "scan": 4,       # v4: mesh surface samples seeded alike for every file (not by source id); v3: stable source ids; mesh surface samples as float32 offsets from a corner
    "register": 3,   # v3: reproducible coarse consensus (tasks.register.sac), samples in coordinate order; v2: surface target, modes auto / pinned / off
    "ingest": 5,     # v5: runs carry a content digest; v4: faces longer than the smallest patch side split (conforming); v3: sorted runs, vertex ids, normals
    "partition": 3,  # v3: runs merged in content-digest order, not by name; v2: store schema 2 (vertex ids, ...)
    "labels": 1,
    "outliers": 2,   # v2: flags in outliers.parquet, not in patches.parquet
    "classify": 4,   # v4: point -> mesh cues against the tile's whole surface (+ in-plane and neighbour-relative cues); v3: cue subsets by the points' coordinates, not their rows; v2: points-only patches inside the solid are bad (evidence.inside_solid)
    "regions": 1,
    "region": 4,     # v4: the MLS strips of quality.holdout_* left out of fusion and meshing; v3: zone faces the MLS did not see kept as they are; v2: conformal charts, one vertex-id namespace
    "merge": 3,      # v3: per-face scan-to-model distance and grader score (face_deviation, face_score); v2: faces graded under repair.grades (the regions stage's rule), not grades-else-labels
}


@dataclass
class Done:
    """What a unit's work returns: outputs (paths relative to the work dir) and a small JSON summary."""

    outputs: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    status: str = "done"  # or "empty"


def os_error_message(e: OSError) -> str:
    """One line for a work-dir write failure."""
    what = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
            errno.EROFS: "the work dir is on a read-only file system",
            errno.EACCES: "permission denied", errno.EPERM: "permission denied"}.get(e.errno, e.strerror or str(e))
    where = f" ({e.filename})" if e.filename else ""
    return f"cannot write{where}: {what}"


def reset_peak_rss() -> None:
    """Reset this process's peak RSS (Linux: ``5 > /proc/self/clear_refs``), so that the peak read after a
    unit is that unit's, not the worker's lifetime peak. A no-op where unsupported."""
    with contextlib.suppress(OSError), open("/proc/self/clear_refs", "w") as f:
        f.write("5")


def release_free_memory() -> None:
    """Give freed heap pages back to the OS (glibc ``malloc_trim``) and Arrow's pool its unused buffers, so
    that what earlier units of a long-lived worker freed does not stay in its RSS under the next unit (a
    no-op where unsupported)."""
    import ctypes
    import sys

    if "pyarrow" in sys.modules:
        with contextlib.suppress(Exception):
            sys.modules["pyarrow"].default_memory_pool().release_unused()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def peak_rss_mb() -> float:
    """Peak RSS (VmHWM) of this process since the last reset, MiB; NaN when unknown."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return round(int(line.split()[1]) / 1024, 1)
    except (OSError, ValueError):
        pass
    return float("nan")


def unit_params(stage: str, params: dict) -> str:
    """The parameter hash recorded for a unit of ``stage``."""
    return params_hash({**params, "_stage_version": STAGE_VERSIONS[stage]})


def failure_message(e: InputError | OSError) -> str:
    """One line for an expected failure: a bad input's own message, or what a work-dir write hit."""
    return str(e) if isinstance(e, InputError) else os_error_message(e)


class _Step:
    """Wall and CPU clock and peak RSS of one unit of work, from construction to :meth:`summary`."""

    def __init__(self) -> None:
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        release_free_memory()
        reset_peak_rss()

    def seconds(self) -> float:
        return time.perf_counter() - self.t0

    def summary(self) -> dict:
        return {"peak_rss_mb": peak_rss_mb(), "cpu_seconds": round(time.process_time() - self.c0, 3)}


_ON_RECORDED: ContextVar[Callable[[str, str], None] | None] = ContextVar("ms3d_on_recorded", default=None)


@contextlib.contextmanager
def on_unit_recorded(hook: Callable[[str, str], None]) -> Iterator[None]:
    """Call ``hook(stage, unit)`` after each unit's manifest record is written inside the block (this thread
    and context): a work dir on a bucket publishes each unit as it finishes, not when its task returns, so a
    killed worker loses at most the unit in progress."""
    token = _ON_RECORDED.set(hook)
    try:
        yield
    finally:
        _ON_RECORDED.reset(token)


def _recorded(stage: str, unit: str) -> None:
    hook = _ON_RECORDED.get()
    if hook is not None:
        hook(stage, unit)


def record_step(wd: WorkDir, stage: str, unit: str, work: Callable[[], dict], fingerprint: str = "",
                params: str = "") -> dict:
    """Run a step that is not skipped by fingerprint (a campus-wide step, an export node) and record it.

    ``work`` returns a dict; its scalar values (plus peak RSS and CPU seconds) become the record's summary
    and its ``status`` (default "done") the record's status. An expected failure (InputError, OSError) is
    returned as ``{"status": "failed", "error": "<stage>: <one line>"}`` and recorded as failed; anything
    else is a bug and propagates. Returns ``{"status", **work's dict}`` on success.
    """
    step = _Step()
    try:
        out = work()
    except (InputError, OSError) as e:
        msg = f"{stage}: {failure_message(e)}"
        with contextlib.suppress(OSError):  # a full disk may refuse the record too; the result still says it
            write_record(wd, ManifestRecord(stage, unit, "failed", fingerprint, params, error=msg,
                                            seconds=step.seconds()))
        _recorded(stage, unit)
        return {"status": "failed", "error": msg}
    status = out.get("status", "done")
    summary = {k: v for k, v in out.items() if isinstance(v, (int, float, str, bool)) or v is None}
    summary |= step.summary()
    write_record(wd, ManifestRecord(stage, unit, status, fingerprint, params, seconds=step.seconds(),
                                    summary=summary))
    _recorded(stage, unit)
    return {**out, "status": status}


def skipped_summary(rec: ManifestRecord) -> dict:
    """The unit summary of a unit skipped because ``rec`` (its current record) says it is done."""
    return {**rec.summary, "unit": rec.unit, "status": rec.status, "skipped": True, "seconds": rec.seconds}


def pending_units(wd: WorkDir, stage: str, fingerprints: dict[str, str], params: dict
                  ) -> tuple[list[str], list[dict]]:
    """Which units of ``stage`` must run, decided from ONE read of the stage's records.

    fingerprints: {unit: input fingerprint}, computed by the stage exactly as its run function does;
    params: the stage's parameter dict (as given to :func:`run_unit`). Returns (units to run, in the
    order given; the :func:`skipped_summary` of every other unit). A unit runs unless its record is
    current (:func:`storage.workdir.manifest.record_is_current`), so the plan skips exactly what
    :func:`run_unit` would; run_unit still checks each unit it is given, so a wrong plan costs time,
    never correctness.
    """
    ph = unit_params(stage, params)
    records = read_stage_records(wd, stage)
    run, skipped = [], []
    for unit, fp in fingerprints.items():
        rec = records.get(unit)
        if record_is_current(wd, rec, fp, ph):
            skipped.append(skipped_summary(rec))
        else:
            run.append(unit)
    return run, skipped


class MustRun(Exception):
    """Raised by :func:`run_unit` inside :func:`planning` for a unit that is not current: it must run."""

    def __init__(self, stage: str, unit: str):
        super().__init__(f"{stage} {unit} must run")
        self.stage, self.unit = stage, unit


class _Plan:
    """The records of each stage, read once (on the first unit of that stage) for a planning pass."""

    def __init__(self, wd: WorkDir):
        self.wd, self.records = wd, {}

    def current(self, stage: str, unit: str, fingerprint: str, phash: str) -> ManifestRecord:
        """The unit's current record; raises MustRun when there is none."""
        if stage not in self.records:
            self.records[stage] = read_stage_records(self.wd, stage)
        rec = self.records[stage].get(unit)
        if not record_is_current(self.wd, rec, fingerprint, phash):
            raise MustRun(stage, unit)
        return rec


_PLANNING: ContextVar[_Plan | None] = ContextVar("ms3d_planning", default=None)


@contextlib.contextmanager
def planning(wd: WorkDir) -> Iterator[None]:
    """Plan instead of run: inside, :func:`run_unit` returns the :func:`skipped_summary` of a current unit
    and raises :class:`MustRun` for any other, without running its work. A stage's run function called
    here computes its fingerprints exactly as when it runs, so the units it returns skipped are exactly
    those a task would skip; each stage's records are read once (:func:`read_stage_records`).

    A run function's own steps before its ``run_unit`` (a stat, removing a stale side table) happen here
    too, as they would in the task; they are idempotent.
    """
    token = _PLANNING.set(_Plan(wd))
    try:
        yield
    finally:
        _PLANNING.reset(token)


def is_planning() -> bool:
    """Whether this code runs inside :func:`planning` (e.g. to leave out a test's fault-injection delay)."""
    return _PLANNING.get() is not None


def run_unit(wd: WorkDir, stage: str, unit: str, fingerprint: str, params: dict,
             work: Callable[[], Done], on_fail: Callable[[], None] | None = None) -> dict:
    """Skip ``unit`` if done and unchanged, else run ``work`` and record the outcome.

    Returns a summary dict with at least ``unit``, ``status`` ("done", "empty", "failed") and
    ``skipped``; a failure adds ``error`` (one line). ``on_fail`` runs after a failure (e.g. to mark a
    stale output); it must not raise. Inside :func:`planning`, raises :class:`MustRun` instead of running.
    """
    ph = unit_params(stage, params)
    plan = _PLANNING.get()
    if plan is not None:
        return skipped_summary(plan.current(stage, unit, fingerprint, ph))
    old = read_record(wd, stage, unit)
    if record_is_current(wd, old, fingerprint, ph):
        return skipped_summary(old)
    redo = redo_reason(wd, old, fingerprint, ph) if old is not None else ""
    step = _Step()
    try:
        out = work()
    except EmptyTileError as e:
        out = Done(status="empty", summary={"reason": e.problem})
    except (InputError, OSError) as e:
        msg = failure_message(e)
        secs = step.seconds()
        with contextlib.suppress(OSError):  # a full disk may refuse the record too; the result still says it
            write_record(wd, ManifestRecord(stage, unit, "failed", fingerprint, ph, error=msg, seconds=secs))
        if on_fail is not None:
            on_fail()
        _recorded(stage, unit)
        return {"unit": unit, "status": "failed", "error": msg, "skipped": False, "seconds": secs}
    secs = step.seconds()
    summary = {**out.summary, "unit": unit, "status": out.status, **step.summary(), **({"redo": redo} if redo else {})}
    write_record(wd, ManifestRecord(stage, unit, out.status, fingerprint, ph, seconds=secs,
                                    outputs=out.outputs, summary=summary))
    _recorded(stage, unit)
    return {**summary, "skipped": False, "seconds": secs}
