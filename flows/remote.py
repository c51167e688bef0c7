"""The flow's side of object storage: inputs named by URL and a work dir on a bucket.

**Work dir by URL** (``work_dir: s3://bucket/prefix``): every process works on its own local mirror of
the recorded work dir (:mod:`storage.objstore.mirror`). A task pulls what its stage reads before it runs and
pushes what it changed as each unit is recorded (:func:`synced`); the driver holds the run lease
(:func:`remote_run`), sweeps unrecorded leftovers, and pulls after each stage and pushes its own writes before
the next (:class:`SyncExecutor`). The driver plans from the records: its pulls bring the manifest records,
JSON documents and small files only (:func:`driver_reads`); sizes, mtimes and digests of the rest come from
the records (:mod:`storage.recorded`), and a larger file is downloaded where the driver reads it. Everything else is the local code, unchanged, on the mirror. Each process writes
its cumulative object-store figures under its cache folder when the driver's hold ends and after each task
(:func:`note_io`, :mod:`storage.objstore.iostats`): what a benchmark reads per process.

**Inputs by URL**: local views of the inputs that stages owned by others read through the config
(texture cameras and images, the synth truth beside the labels).

Stages that open input files by their recorded identity call :func:`storage.inputs.remote.local_input`
themselves; the texture step and the quality stage read ``cfg.inputs.images`` / ``cameras`` / ``labels``
as folders, so their tasks get a config whose URLs are replaced by this process's staged copies
(:func:`local_view`). Only those tasks use it: the labels stage keeps the URL (its fingerprint names the
input), and nothing a local view holds is written to the work dir by path. A config without URLs is
returned as it is (the local path pays one string test per field).
"""

from __future__ import annotations

import contextlib
import functools
import inspect
import logging
import os
from pathlib import Path

from storage.workdir.layout import WorkDir
from tasks.config import CampusConfig

log = logging.getLogger("ms3d.flow")

__all__ = ["EPOCH_KEY", "SyncExecutor", "driver_reads", "is_remote", "local_truth_plan", "local_view", "mirror_for",
           "note_io", "remote_run", "synced", "uses_urls", "with_epoch", "work_dir_of"]

SWEEP_GRACE_S = 600.0  # unrecorded objects younger than this may belong to a task of a killed run still writing
DRIVER_PULL_MAX_BYTES = 16 << 10  # the driver downloads files up to this size when it pulls; larger ones when read
DRIVER_PULLS = ("manifest.d/", "labels/")  # and these folders whole (records, the user's labels), and every JSON


def is_remote(cfg_or_url) -> bool:
    """Whether a config's work dir (or a work-dir string) is an object-store URL."""
    from storage.inputs.location import is_url

    return is_url(getattr(cfg_or_url, "work_dir", cfg_or_url))


def cache_dir() -> Path:
    """This process's cache folder (``$MS3D_CACHE`` or ``./.ms3d-cache``): input copies and work-dir mirrors."""
    from storage.inputs.remote import cache_root

    return cache_root().parent


def mirror_for(url: str):
    """This process's :class:`storage.objstore.mirror.Mirror` of the work dir ``url``."""
    from storage.objstore.mirror import mirror_of
    from storage.objstore.store import open_store

    return mirror_of(open_store(url), cache_dir())


def work_dir_of(cfg: CampusConfig) -> WorkDir:
    """The WorkDir the local code uses: the configured folder, or this process's mirror of a URL."""
    if not is_remote(cfg):
        return WorkDir(cfg.work_dir)
    return WorkDir(mirror_for(cfg.work_dir).root)


def note_io(role: str) -> None:
    """Write this process's cumulative object-store figures under its cache folder
    (:mod:`storage.objstore.iostats`); a figure that cannot be written is only logged."""
    from storage.objstore.iostats import write_io_stats

    try:
        write_io_stats(cache_dir(), role)
    except OSError as e:
        log.warning("could not write this process's I/O figures: %s", e)


def _cfg_json_of(args, kwargs) -> dict | None:
    cj = kwargs.get("cfg_json")
    if cj is None:
        cj = next((a for a in args if isinstance(a, dict) and "work_dir" in a and "inputs" in a), None)
    return cj


EPOCH_KEY = "_ms3d_run_epoch"  # the run epoch the driver hands its tasks, inside their config dict


def with_epoch(value, epoch: int | None):
    """``value`` with the run epoch added to it if it is a task's config dict (a dict with "work_dir" and
    "inputs"); anything else as it is."""
    if epoch is not None and isinstance(value, dict) and "work_dir" in value and "inputs" in value:
        return {**value, EPOCH_KEY: epoch}
    return value


def _split_epoch(args: tuple, kwargs: dict) -> tuple[tuple, dict, int | None]:
    """(args, kwargs) with the run epoch taken out of the config dict, and the epoch (None when absent)."""
    epoch = None

    def strip(v):
        nonlocal epoch
        if isinstance(v, dict) and EPOCH_KEY in v:
            epoch = int(v[EPOCH_KEY])
            return {k: x for k, x in v.items() if k != EPOCH_KEY}
        return v

    return tuple(strip(a) for a in args), {k: strip(v) for k, v in kwargs.items()}, epoch


def synced(spec):
    """Decorate a stage's task function (``spec``: its ``tasks.stages.StageSpec``): with a work dir by URL,
    pull what the declaration says the task reads (``spec.reads_for`` its batch, or :func:`campus_reads`)
    before, and push after (a task that raises pushes nothing: its units are not recorded and run again);
    a worker then deletes its mirror's unchanged copies (``Mirror.release``: they stay in its content cache
    and come back when a later task reads them), so its scratch holds one copy of what it read. The task
    acts under the run epoch the driver gave it: it stops (RunSuperseded) without reading or
    committing when a later run has begun. Inside planning it only runs ``fn``."""
    def decorate(fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            from storage.objstore.iostats import TaskMeter
            from tasks.units import is_planning, on_unit_recorded

            args, kwargs, epoch = _split_epoch(args, kwargs)
            cj = _cfg_json_of(args, kwargs)
            if cj is None or not is_remote(cj.get("work_dir")) or is_planning():
                return fn(*args, **kwargs)
            mirror = mirror_for(cj["work_dir"])
            if epoch is not None:
                mirror.epoch = epoch
                mirror.check_current()
            first = args[0] if args else kwargs.get(next(iter(inspect.signature(fn).parameters)))
            reads = spec.reads_for(first if isinstance(first, list) else [])
            skips = spec.skips
            label = getattr(fn, "__name__", "task")
            try:
                with TaskMeter(label) as meter:
                    meter.timed("pull", mirror.pull, (lambda rel: rel.startswith(reads)) if reads is not None else
                                campus_reads(mirror, skips))
                    with on_unit_recorded(lambda stage, unit: meter.timed("push", mirror.push,
                                                                          f"{label} {stage} {unit}")):
                        out = fn(*args, **kwargs)  # each unit is published as it is recorded
                    meter.timed("push", mirror.push, label)
                if not mirror.lazy:  # a worker keeps what its content cache holds, not a mirror (the driver's
                    mirror.release()  # inline tasks keep theirs: it plans from them)
            finally:
                note_io("worker")
            return out
        return wrapper
    return decorate


@contextlib.contextmanager
def remote_run(cfg: CampusConfig):
    """The driver's hold on a work dir by URL: the run lease, a sweep of unrecorded leftovers older than
    SWEEP_GRACE_S, a pull; at exit (also on error) a push of the driver's writes. Yields the Mirror."""
    from storage.objstore.commit import sweep_unrecorded
    from storage.objstore.epoch import begin_epoch
    from storage.objstore.lock import DEFAULT_TTL_S, run_lock

    mirror = mirror_for(cfg.work_dir)
    mirror.lazy = True  # it downloads what it reads when it reads it (driver_reads)
    ttl_s = float(os.environ.get("MS3D_LEASE_TTL_S", DEFAULT_TTL_S))  # how long a killed run blocks the next
    with run_lock(mirror.store, ttl_s=ttl_s) as lease:
        mirror.lease = lease  # SyncExecutor checks it before every stage's tasks
        if lease is not None:  # the run's epoch: seals what earlier runs committed, fences what they commit late
            mirror.epoch = begin_epoch(mirror.store, lease.token, mirror.record_keys()).number
        _driver_pull(mirror, "driver: pull at start")
        mirror.compact()  # one record for the current state: superseded objects become sweepable
        gone = sweep_unrecorded(mirror.store, grace_s=float(os.environ.get("MS3D_SWEEP_GRACE_S", SWEEP_GRACE_S)))
        if gone:
            log.info("swept %d unrecorded objects of earlier runs from %s", len(gone), mirror.store.describe())
        try:
            yield mirror
        finally:
            mirror.lease = None
            if lease is None or lease.lost is None:  # a run that lost its lease writes nothing more
                mirror.push("driver")
            note_io("driver")
            st = mirror.store.stats
            log.info("work dir %s: driver %d commits, %d files pushed, %d pulled; %d requests, %.1f MB read, "
                     "%.1f MB written", mirror.store.describe(), mirror.stats["commits"], mirror.stats["pushed_files"],
                     mirror.stats["pulled_files"], st.n_requests, st.bytes_read / 1e6, st.bytes_written / 1e6)


def driver_reads(mirror):
    """What the driver downloads when it pulls (a predicate on relative paths): the manifest records, the user's
    labels, every JSON document and every file of at most DRIVER_PULL_MAX_BYTES. It plans from the records
    (:mod:`storage.recorded`: sizes, mtimes and digests of the files it has not downloaded) and downloads a
    larger file only where code reads it (a tile store, a merged tile, an LOD mesh)."""
    def wanted(rel: str) -> bool:
        return rel.startswith(DRIVER_PULLS) or rel.endswith(".json") or \
            mirror.files.get(rel, (0, 0))[0] <= DRIVER_PULL_MAX_BYTES
    return wanted


CAMPUS_PULLS = ("report/",)  # a campus-wide task also pulls these folders whole (the report's figures)


def campus_reads(mirror, skips: tuple[str, ...]):
    """What a campus-wide task (no ``reads`` declared: regions, outliers, quality, held-out, report, renders)
    pulls before it runs: what the driver pulls (:func:`driver_reads`: records, JSON documents, small files)
    and ``CAMPUS_PULLS``, none under ``skips``. The tile stores, merged tiles, region meshes and LOD meshes
    it opens come on demand (:func:`storage.recorded.ensure_local` where they are opened), so it downloads
    the bytes it reads, not the work dir."""
    small = driver_reads(mirror)
    return lambda rel: not rel.startswith(skips) and (small(rel) or rel.startswith(CAMPUS_PULLS))


def _driver_pull(mirror, label: str) -> None:
    """The driver's pull of ``mirror`` (:func:`driver_reads`), timed and counted under ``label``
    (:mod:`storage.objstore.iostats`)."""
    from storage.objstore.iostats import TaskMeter

    with TaskMeter(label) as meter:
        meter.timed("pull", mirror.pull, driver_reads(mirror))
    mirror.release(keep=driver_reads(mirror))  # what it downloaded to read once (a tile's tables) stays in the cache


def _check_lease(mirror) -> None:
    """Stop the run (LeaseLost, one line) when its lease was taken over: another run owns the work dir."""
    if (lease := getattr(mirror, "lease", None)) is not None:
        lease.check()


class SyncExecutor:
    """An executor (``flows.executors``) of a run whose work dir is a URL: the driver pushes its writes
    before tasks start and pulls their results when they are collected. Tasks in ``RELATIVE_TASKS`` (export
    nodes, whose jobs name work-dir paths) get their jobs with paths relative to the work dir and the work
    dir's URL (``cfg_json``), and run on the workers like every other task."""

    RELATIVE_TASKS = ("export-nodes",)

    def __init__(self, inner, mirror):
        self.inner, self.mirror = inner, mirror

    @property
    def task_runs(self) -> int:
        return getattr(self.inner, "task_runs", 0)

    def slots(self) -> int:
        return getattr(self.inner, "slots", lambda: 0)()

    def map(self, tsk, batches: list, label: str, **consts):
        _check_lease(self.mirror)
        if getattr(tsk, "name", "") in self.RELATIVE_TASKS:
            from tasks.export import relocate_jobs

            batches = [relocate_jobs(b, self.mirror.root, Path()) for b in batches]
            consts = {**consts, "cfg_json": {"work_dir": self.mirror.store.url, "inputs": {}}}
        self.mirror.push("driver")
        epoch = getattr(self.mirror, "epoch", None)
        consts = {k: with_epoch(v, epoch) for k, v in consts.items()}
        return _Pulled(self.inner.map(tsk, batches, label, **consts), self.mirror)

    def submit(self, tsk, *args):
        _check_lease(self.mirror)
        self.mirror.push("driver")
        epoch = getattr(self.mirror, "epoch", None)
        return _Pulled(self.inner.submit(tsk, *(with_epoch(a, epoch) for a in args)), self.mirror)

    def recycle_workers(self, over_mb: float) -> dict:
        return {"restarted": 0, "largest_mb": 0.0}  # a restarted worker would pull its mirror again


class _Pulled:
    """A mapped or submitted result whose collection pulls the mirror up to date."""

    def __init__(self, inner, mirror):
        self.inner, self.mirror = inner, mirror

    def results(self):
        out = self.inner.results()
        _check_lease(self.mirror)
        _driver_pull(self.mirror, "driver: pull after tasks")
        return out

    def result(self):
        out = self.inner.result()
        _check_lease(self.mirror)
        _driver_pull(self.mirror, "driver: pull after tasks")
        return out


def uses_urls(cfg: CampusConfig) -> bool:
    """Whether any input of ``cfg`` is named by an object-store URL."""
    from storage.inputs.location import is_url

    i = cfg.inputs
    return any(is_url(p) for p in [*i.mesh, *i.points, i.labels, i.images, i.cameras])


def local_view(cfg: CampusConfig, what: str) -> CampusConfig:
    """``cfg`` with the inputs ``what`` needs staged locally: "texture" (images and cameras; without them
    configured, an ``images`` folder beside the first mesh URL), "cameras" (the cameras alone, as the texture
    step finds them: what the driver fingerprints the regions by) or "truth" (the labels file and the
    ``truth/`` folder beside its folder, where the synth campus keeps its truth mesh)."""
    from storage.inputs.location import is_url
    from storage.inputs.remote import input_exists, local_input

    i = cfg.inputs
    change: dict = {}
    if what == "cameras":
        cams, images = i.cameras, i.images
        if cams is None and images is None and i.mesh and is_url(i.mesh[0]):
            images = i.mesh[0].rstrip("/").rsplit("/", 1)[0] + "/images"
        if cams is None and is_url(images) and input_exists(images.rstrip("/") + "/cameras.json"):
            cams = images.rstrip("/") + "/cameras.json"
        if is_url(cams):
            change["cameras"] = local_input(cams)
    elif what == "texture":
        images, cams = i.images, i.cameras
        if images is None and cams is None and i.mesh and is_url(i.mesh[0]):
            guess = i.mesh[0].rstrip("/").rsplit("/", 1)[0] + "/images"
            images = guess if input_exists(guess + "/cameras.json") else None
        for key, value in (("images", images), ("cameras", cams)):
            if is_url(value):
                change[key] = local_input(value)
    elif what == "truth" and is_url(i.labels):
        change["labels"] = local_input(i.labels)
        truth = i.labels.rsplit("/", 2)[0] + "/truth"
        if truth.count("/") > 3 and input_exists(truth):
            local_input(truth)
    if not change:
        return cfg
    return cfg.model_copy(update={"inputs": i.model_copy(update=change)})


def local_truth_plan(cfg: CampusConfig, plan: dict) -> dict:
    """A quality plan whose ``truth`` folder is this process's staged copy (the driver planned it with
    its own); ``plan`` unchanged when the labels are not a URL."""
    from storage.inputs.location import is_url

    if not is_url(cfg.inputs.labels):
        return plan
    from tasks.quality import truth_dir_of

    truth = truth_dir_of(local_view(cfg, "truth"))
    return {**plan, "truth": str(truth)} if truth is not None else plan
