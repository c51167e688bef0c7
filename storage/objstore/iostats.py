"""What one process has moved through object storage, written where a benchmark can read it back.

Every process that works on a work dir by URL (the flow's driver, each Dask worker after each task) writes
its cumulative figures to ``{cache}/io-stats/{pid}-{instance}.json`` (``cache``: its ``MS3D_CACHE``), each
time replacing the previous file atomically (:func:`write_io_stats`, one small JSON write: no request to the
store, no walk of the cache). A benchmark then reads each process's file next to a walk of that process's
cache folder: bytes downloaded against bytes held on scratch.

::

    {"pid": 4242, "instance": "ab12cd34", "roles": ["worker"], "cache": "/scratch/w0/cache",
     "updated_utc": 1767225600.0,
     "work_dir": {"bytes_read": ..., "bytes_written": ..., "n_requests": ..., "requests": {"GetObject": ...}},
     "inputs":   {...},          the input buckets (storage.inputs.remote): staged meshes, points, images
     "total":    {...},          both
     "mirror":   {"pulled_files": ..., "pushed_files": ..., "commits": ..., "records_read": ..., "cache_hits": ...},
     "cas":      {"hits": ..., "misses": ..., "bytes_fetched": ..., "evicted": ...},
     "tasks":    {"partition_task": {"runs": 3, "seconds": ..., "pull_s": ..., "push_s": ...,
                                     "bytes_read": ..., "bytes_written": ..., "n_requests": ...}, ...}}

Figures are sums over the process's stores, mirrors (one per thread) and content caches; a store shared by
several mirrors counts once. ``tasks`` splits them by task (:class:`TaskMeter`: the process's totals before
and after each task, its wall seconds and the seconds spent pulling and pushing); a task's figures are its
own when the process runs one task at a time (``--nthreads 1``, as the recipes do).
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Self

from storage.atomic import write_json_atomic

IO_STATS_DIR = "io-stats"
_ROLES: set[str] = set()
_TASKS: dict[str, Counter] = {}
_LOCK = threading.RLock()
_MOVED = ("bytes_read", "bytes_written", "n_requests")


def _stores_figures(stores) -> dict:
    """{bytes_read, bytes_written, n_requests, requests: {op: n}} summed over distinct ``stores``."""
    requests: Counter = Counter()
    read = written = 0
    for s in {id(s): s for s in stores}.values():
        requests.update(s.stats.requests)
        read += s.stats.bytes_read
        written += s.stats.bytes_written
    return {"bytes_read": read, "bytes_written": written, "n_requests": sum(requests.values()),
            "requests": dict(sorted(requests.items()))}


def process_io() -> dict:
    """This process's cumulative object-store figures (the module docstring's document, without the header)."""
    from storage.inputs.remote import input_stores
    from storage.objstore.cas import content_caches
    from storage.objstore.mirror import live_mirrors

    mirrors = live_mirrors()
    work, inputs = [m.store for m in mirrors], input_stores()
    mirror = Counter()
    for m in mirrors:
        mirror.update(m.stats)
    cas = Counter()
    for c in content_caches():
        cas.update(c.stats)
    with _LOCK:
        tasks = {k: dict(v) for k, v in sorted(_TASKS.items())}
    return {"work_dir": _stores_figures(work), "inputs": _stores_figures(inputs),
            "total": _stores_figures(work + inputs), "mirror": dict(mirror), "cas": dict(cas), "tasks": tasks}


def _moved() -> dict:
    total = process_io_totals()
    return {k: total[k] for k in _MOVED}


def process_io_totals() -> dict:
    """{bytes_read, bytes_written, n_requests, requests} of every store of this process (work dir and inputs)."""
    from storage.inputs.remote import input_stores
    from storage.objstore.mirror import live_mirrors

    return _stores_figures([m.store for m in live_mirrors()] + input_stores())


class TaskMeter:
    """What one task moved and how long it took, added to this process's ``tasks`` figures under ``label``
    when the block ends (also when it raises)::

        with TaskMeter("merge_task") as meter:
            meter.timed("pull", mirror.pull)
            ...
    """

    def __init__(self, label: str):
        self.label = label
        self.spent = Counter()

    def __enter__(self) -> Self:
        self.t0, self.before = time.perf_counter(), _moved()
        return self

    def timed(self, what: str, fn, *args, **kwargs):
        """``fn(*args, **kwargs)``, its seconds added to ``{what}_s``."""
        t0 = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.spent[f"{what}_s"] += time.perf_counter() - t0

    def __exit__(self, *exc) -> None:
        after = _moved()
        add = Counter({k: after[k] - self.before[k] for k in _MOVED})
        add.update({"runs": 1, "seconds": time.perf_counter() - self.t0, "pull_s": 0.0, "push_s": 0.0})
        add.update(self.spent)
        with _LOCK:
            _TASKS.setdefault(self.label, Counter()).update(add)


def io_stats_path(cache: str | Path) -> Path:
    """This process instance's figures file under the cache folder ``cache``."""
    from storage.objstore.mirror import process_instance

    return Path(cache) / IO_STATS_DIR / f"{os.getpid()}-{process_instance()}.json"


def write_io_stats(cache: str | Path, role: str) -> Path:
    """Write this process's figures (:func:`process_io`) under ``cache``, tagged with ``role`` ("driver",
    "worker"; a process that is both, e.g. an inline run, lists both). Returns the file written."""
    from storage.objstore.mirror import process_instance

    with _LOCK:
        _ROLES.add(role)
        doc = {"pid": os.getpid(), "instance": process_instance(), "roles": sorted(_ROLES),
               "cache": str(Path(cache).absolute()), "updated_utc": time.time(), **process_io()}
        path = io_stats_path(cache)
        write_json_atomic(path, doc)
    return path


def read_io_stats(cache: str | Path) -> list[dict]:
    """Every process's figures written under ``cache`` (in file-name order; unreadable files left out)."""
    d = Path(cache) / IO_STATS_DIR
    out = []
    for p in sorted(d.glob("*.json")) if d.is_dir() else []:
        if p.name.startswith("."):
            continue  # a file being written (storage.atomic)
        try:
            out.append(json.loads(p.read_text()))
        except (OSError, ValueError):
            continue
    return out


__all__ = ["IO_STATS_DIR", "TaskMeter", "io_stats_path", "process_io", "process_io_totals", "read_io_stats",
           "write_io_stats"]
