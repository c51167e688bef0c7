"""A projection of a campus run on a bucket to a larger campus, from the figures one run measured per task.

Inputs: each task's measured figures, summed over the workers (``tasks`` of :mod:`storage.objstore.iostats`:
runs, seconds, seconds pulling and pushing, bytes read and written, requests), the driver's, and the campus's
area and point count. Scaling assumptions (printed with the result):

- units that cover the campus (files, ingest units, tiles, regions, nodes) scale with the area: ``k_area``;
- the bytes of one such unit, and its compute, scale with the point density: ``k_density``; the work dir
  scales with both (``k_bytes = k_area * k_density``, the ratio of point counts);
- a task whose stage declares what it reads (``StageSpec.reads``) reads its units only: its bytes and compute
  per task scale with ``k_density``, its task count with ``k_area``, its requests per task stay;
- a task that pulls the work dir (``reads`` None: campus-wide steps, repair batches, report) reads per task
  ``k_bytes`` times what it read here, in ``k_area`` times the requests; campus-wide steps keep their task
  count and their compute scales with ``k_bytes``; repair keeps ``4 x workers`` batches
  (``tasks.stages.balanced_region_batches``) over ``k_bytes`` times the compute;
- every process fetches one object at a time: each request costs ``latency`` and each byte ``1 / bandwidth``;
- stages run one after the other, each in ``ceil(tasks / workers)`` rounds of its mean task; the driver's
  transfers are serial, between the stages; the driver's planning compute is left out.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

MiB, GB, TB = 2**20, 1e9, 1e12


@dataclass(frozen=True)
class Scale:
    """The measured campus and the target: area (km²), points, workers; transfer figures of the store."""

    area_km2: float
    points: float
    target_km2: float
    target_points: float
    workers: int
    latency_s: float
    bandwidth_bps: float

    @property
    def k_area(self) -> float:
        return self.target_km2 / self.area_km2

    @property
    def k_bytes(self) -> float:
        return self.target_points / self.points

    @property
    def k_density(self) -> float:
        return self.k_bytes / self.k_area

    def transfer_s(self, nbytes: float, requests: float) -> float:
        return requests * self.latency_s + nbytes / self.bandwidth_bps


def task_specs() -> dict:
    """{task function name: its StageSpec} of the campus flow's tasks."""
    from flows import tasks

    found = [getattr(tasks, n) for n in dir(tasks)]
    return {t.fn.__name__: t.spec for t in found if getattr(t, "spec", None) is not None and hasattr(t, "fn")}


def sum_tasks(docs: list[dict]) -> dict[str, Counter]:
    """{task label: figures summed over the processes' io-stats documents ``docs``}."""
    out: dict[str, Counter] = {}
    for d in docs:
        for label, fig in (d.get("tasks") or {}).items():
            out.setdefault(label, Counter()).update(fig)
    return out


@dataclass
class StageProjection:
    label: str
    how: str
    tasks: float
    read: float  # bytes per task
    written: float
    requests: float  # per task
    compute_s: float  # per task
    rounds: int
    time_s: float


def project_task(label: str, fig: Counter, spec, s: Scale) -> StageProjection:
    """One task label's projection (module docstring)."""
    runs = max(int(fig["runs"]), 1)
    compute = max(fig["seconds"] - fig["pull_s"] - fig["push_s"], 0.0) / runs
    read, written, req = fig["bytes_read"] / runs, fig["bytes_written"] / runs, fig["n_requests"] / runs
    if spec is not None and spec.reads is not None:
        how, tasks = "its units", runs * s.k_area
        read, written, compute = read * s.k_density, written * s.k_density, compute * s.k_density
    elif spec is not None and spec.unit == "region":
        how, tasks = "work dir, 4 x workers batches", 4 * s.workers
        read, written, req = read * s.k_bytes, written * s.k_density * s.k_area * runs / tasks, req * s.k_area
        compute = compute * runs * s.k_bytes / tasks
    else:
        how, tasks = "work dir", runs
        read, written, req, compute = read * s.k_bytes, written * s.k_bytes, req * s.k_area, compute * s.k_bytes
    rounds = math.ceil(tasks / s.workers)
    per_task = compute + s.transfer_s(read + written, req)
    return StageProjection(label, how, tasks, read, written, req, compute, rounds, rounds * per_task)


def print_projection(s: Scale, worker_docs: list[dict], driver: dict, rerun_driver: dict, held_ratio: float) -> None:
    """Print the projection of the measured run (``worker_docs``: the workers' io-stats documents; ``driver``,
    ``rerun_driver``: {"read", "written", "requests", "held"} of the first run's driver and of a no-op rerun's
    fresh driver; ``held_ratio``: the workers' bytes held on scratch per byte read)."""
    specs = task_specs()
    rows = [project_task(label, fig, specs.get(label), s) for label, fig in sorted(sum_tasks(worker_docs).items())]
    print(f"\nprojection to {s.target_km2:g} km², {s.target_points:.3g} points, {s.workers} workers "
          f"(measured: {s.area_km2:.4f} km², {s.points:.4g} points)")
    print(f"  k_area {s.k_area:.1f} (units), k_density {s.k_density:.2f} (bytes and compute per unit), "
          f"k_bytes {s.k_bytes:.0f} (work dir); {s.latency_s * 1e3:.0f} ms per request, "
          f"{s.bandwidth_bps / 1e6:.0f} MB/s per process, one request at a time")
    print(f"  {'task':<26} {'reads':<30} {'tasks':>8} {'GB/task':>9} {'req/task':>9} {'compute s':>10} "
          f"{'rounds':>6} {'stage h':>8}")
    print("  (compute: a task's wall seconds less its pull and push seconds, as measured, scaled as above)")
    for r in rows:
        print(f"  {r.label:<26} {r.how:<30} {r.tasks:>8.0f} {(r.read + r.written) / GB:>9.3f} {r.requests:>9.0f} "
              f"{r.compute_s:>10.1f} {r.rounds:>6} {r.time_s / 3600:>8.2f}")
    worker_bytes = sum(r.tasks * (r.read + r.written) for r in rows)
    worker_req = sum(r.tasks * r.requests for r in rows)
    d_bytes = (driver["read"] + driver["written"]) * s.k_bytes
    d_req = driver["requests"] * s.k_area
    d_time = s.transfer_s(d_bytes, d_req)
    print(f"  first run, transfer volume: workers {worker_bytes / TB:.2f} TB in {worker_req:,.0f} requests; driver "
          f"{d_bytes / TB:.2f} TB in {d_req:,.0f} requests; total {(worker_bytes + d_bytes) / TB:.2f} TB")
    read_per_worker = sum(r.tasks * r.read for r in rows) / s.workers
    largest = max((r.read for r in rows), default=0.0)
    scratch = held_ratio * max(read_per_worker, largest)
    print(f"  scratch per worker: {scratch / GB:,.0f} GB (held/read {held_ratio:.2f} x max(its share of the "
          f"workers' reads {read_per_worker / GB:,.0f} GB, the largest task's read {largest / GB:,.0f} GB)); "
          f"driver {driver['held'] * s.k_bytes / GB:,.0f} GB")
    crit = sum(r.time_s for r in rows) + d_time
    print(f"  critical path on {s.workers} workers: {crit / 3600:.1f} h (stages {sum(r.time_s for r in rows) / 3600:.1f} h, "
          f"driver transfers {d_time / 3600:.1f} h)")
    r_bytes = rerun_driver["read"] * s.k_bytes
    r_req = rerun_driver["requests"] * s.k_area
    print(f"  no-op rerun from a fresh driver: {r_bytes / GB:,.1f} GB in {r_req:,.0f} requests, "
          f"{s.transfer_s(r_bytes, r_req) / 3600:.2f} h of transfers")


__all__ = ["Scale", "print_projection", "project_task", "sum_tasks", "task_specs"]
