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
     "cas":      {"hits": ..., "misses": ..., "bytes_fetched": ..., "evicted": ...}}

Figures are sums over the process's stores, mirrors (one per thread) and content caches; a store shared by
several mirrors counts once.
"""

from __future__ import annotations

import json
import os
import threading
import time
from collections import Counter
from pathlib import Path

from storage.atomic import write_json_atomic

IO_STATS_DIR = "io-stats"
_ROLES: set[str] = set()
_LOCK = threading.Lock()


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
    return {"work_dir": _stores_figures(work), "inputs": _stores_figures(inputs),
            "total": _stores_figures(work + inputs), "mirror": dict(mirror), "cas": dict(cas)}


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


__all__ = ["IO_STATS_DIR", "io_stats_path", "process_io", "read_io_stats", "write_io_stats"]
