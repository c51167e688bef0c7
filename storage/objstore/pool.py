"""Concurrent requests to an object store: the latency of one GET or PUT (7 ms on loopback, 20-100 ms to a
remote bucket) is paid once per batch of ``io_threads()`` objects instead of once per object.

The store's client is shared by the threads (s3fs runs every request on its one event loop; the threads only
wait). A local store gains nothing and runs in the calling thread.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TypeVar

T = TypeVar("T")
R = TypeVar("R")

DEFAULT_IO_THREADS = 8


def io_threads() -> int:
    """Requests in flight per call (``MS3D_IO_THREADS``, default 8; 1 turns concurrency off)."""
    try:
        return max(1, int(os.environ.get("MS3D_IO_THREADS", DEFAULT_IO_THREADS)))
    except ValueError:
        return DEFAULT_IO_THREADS


def io_map(fn: Callable[[T], R], items: Sequence[T], concurrent: bool = True) -> list[R | BaseException]:
    """``fn`` over ``items``, up to :func:`io_threads` at a time; one entry per item, in order: its result,
    or the exception it raised (every item is tried; the caller decides what a failure means)."""
    def one(x: T) -> R | BaseException:
        try:
            return fn(x)
        except Exception as exc:  # noqa: BLE001 - returned, not raised: the other items still run
            return exc

    n = min(io_threads(), len(items)) if concurrent else 1
    if n <= 1:
        return [one(x) for x in items]
    with ThreadPoolExecutor(max_workers=n, thread_name_prefix="ms3d-io") as pool:
        return list(pool.map(one, items))


def first_error(results: list) -> BaseException | None:
    """The first exception in ``results`` of :func:`io_map`, or None."""
    return next((r for r in results if isinstance(r, BaseException)), None)
