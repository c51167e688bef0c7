"""A no-shared-disk Dask cluster for the benchmarks (as ``tests/flows/test_s3_cluster.py`` builds it): a
``dask scheduler`` and N ``dask worker`` processes on 127.0.0.1, each in its own empty working directory with its
own ``MS3D_CACHE``, sharing nothing but the S3 endpoint; and what each process moved and holds on scratch.

Each process writes its cumulative figures to ``{MS3D_CACHE}/io-stats/`` (:mod:`storage.objstore.iostats`); what
it holds is a walk of its ``MS3D_CACHE`` folder (every file once, by inode).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Self

from storage.objstore.iostats import read_io_stats

ROOT = Path(__file__).resolve().parents[1]
WORKER_ENV = {"OMP_NUM_THREADS": "1", "MALLOC_TRIM_THRESHOLD_": str(64 << 20), "MALLOC_MMAP_THRESHOLD_": str(32 << 20)}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def process_env(cache: Path, base: dict | None = None) -> dict:
    """The environment of one cluster process (or driver) whose scratch is ``cache``."""
    return {**(base if base is not None else os.environ), **WORKER_ENV, "MS3D_CACHE": str(cache),
            "PYTHONPATH": str(ROOT), "PREFECT_LOGGING_LEVEL": "WARNING"}


def held_bytes(folder: Path) -> int:
    """Bytes of every file under ``folder`` (each inode once); 0 when it does not exist."""
    seen, total = set(), 0
    for dirpath, _, files in os.walk(folder):
        for name in files:
            try:
                st = os.lstat(os.path.join(dirpath, name))
            except OSError:
                continue
            if (st.st_dev, st.st_ino) not in seen:
                seen.add((st.st_dev, st.st_ino))
                total += st.st_size
    return total


@dataclass
class ProcessFigures:
    """One process's cumulative figures (its io-stats file; zeros when it wrote none) and its scratch."""

    name: str
    cache: Path
    doc: dict
    held: int

    @classmethod
    def read(cls, name: str, cache: Path) -> list[ProcessFigures]:
        """The figures of every process instance that used ``cache`` (one per io-stats file; one with zeros
        when none wrote one), the scratch counted with the first."""
        docs = read_io_stats(cache) or [{}]
        return [cls(name if len(docs) == 1 else f"{name}#{i}", cache, d, held_bytes(cache) if i == 0 else 0)
                for i, d in enumerate(docs)]

    def moved(self, key: str) -> int:
        return int(self.doc.get("total", {}).get(key, 0))

    @property
    def read_bytes(self) -> int:
        return self.moved("bytes_read")

    @property
    def requests(self) -> int:
        return self.moved("n_requests")

    def minus(self, before: ProcessFigures | None) -> ProcessFigures:
        """These figures less ``before`` (the same process instance, earlier): what it did in between."""
        if before is None or before.doc.get("instance") != self.doc.get("instance"):
            return self
        doc = {**self.doc, "total": {k: self.moved(k) - before.moved(k) for k in ("bytes_read", "bytes_written",
                                                                              "n_requests")}}
        return ProcessFigures(self.name, self.cache, doc, self.held)


class DaskCluster:
    """A scheduler and ``n`` workers (one thread each), each process in ``root/{name}`` with its cache in
    ``root/{name}/cache``. Use as a context manager; ``address`` is the scheduler's."""

    def __init__(self, root: Path, n: int, env: dict, memory_limit: str = "auto"):
        self.root, self.n, self.env, self.memory_limit = Path(root), n, env, memory_limit
        self.procs: dict[str, subprocess.Popen] = {}
        self._logs = []
        self.address = f"tcp://127.0.0.1:{_free_port()}"

    def cache(self, name: str) -> Path:
        return self.root / name / "cache"

    @property
    def workers(self) -> list[str]:
        return [f"worker{i}" for i in range(self.n)]

    def _start(self, name: str, args: list[str]) -> None:
        cwd = self.root / name
        cwd.mkdir(parents=True)
        log = open(self.root / f"{name}.log", "wb")  # noqa: SIM115 - closed in __exit__
        self._logs.append(log)
        self.procs[name] = subprocess.Popen([sys.executable, "-m", "dask", *args], cwd=cwd,
                                            env=process_env(self.cache(name), self.env), stdout=log,
                                            stderr=subprocess.STDOUT)

    def __enter__(self) -> Self:
        port = self.address.rsplit(":", 1)[1]
        self._start("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", port, "--no-dashboard", "--no-show"])
        for i, name in enumerate(self.workers):
            self._start(name, ["worker", self.address, "--host", "127.0.0.1", "--nthreads", "1", "--nworkers", "1",
                               "--memory-limit", self.memory_limit, "--no-dashboard", "--name", f"w{i}"])
        from distributed import Client

        t0 = time.time()
        with Client(self.address, timeout=120) as c:
            c.wait_for_workers(self.n, timeout=180)
        print(f"dask cluster up: scheduler and {self.n} workers in {time.time() - t0:.0f} s ({self.address})")
        return self

    def __exit__(self, *exc) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()
        for p in self.procs.values():
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for log in self._logs:
            log.close()

    def figures(self) -> list[ProcessFigures]:
        """Every worker's figures now."""
        return [f for name in self.workers for f in ProcessFigures.read(name, self.cache(name))]


__all__ = ["DaskCluster", "ProcessFigures", "held_bytes", "process_env"]
