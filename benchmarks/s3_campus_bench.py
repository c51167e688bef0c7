"""A whole campus with its inputs and work dir on S3 (moto's server on 127.0.0.1) against the same campus on
local disk, run side by side: wall time, what each process downloads and holds on scratch, S3 requests per
unit, a projection to a city, and what reading one patch fetches.

1. ``ms3d run`` of the campus on local disk (``--workers`` Dask worker processes);
2. the same inputs uploaded to the local S3 server, ``ms3d run`` with ``--work-dir s3://…`` and every input
   by URL. ``--mode cluster`` (default): on a no-shared-disk cluster as ``tests/flows/test_s3_cluster.py``
   builds it (``benchmarks/_cluster.py``: a ``dask scheduler`` and ``--workers`` ``dask worker`` processes,
   each in its own empty directory with its own ``MS3D_CACHE``; the driver with its own), ``--dask-address``;
   ``--mode local-cluster``: the driver's own local cluster sharing its cache. The wall time ratio S3 / local
   is a figure (goal <= 1.3x);
3. (cluster mode) per process, from the figures each writes under its cache (``storage.objstore.iostats``):
   bytes downloaded, bytes held on scratch (a walk of its ``MS3D_CACHE``), requests, held / read, and
   downloaded as a share of the work dir (the recorded state in the bucket); then the same for a no-op rerun
   from a new driver with a fresh cache, on the same workers. Goals: the fresh driver's no-op rerun downloads
   <= 1 % of the work dir; no process holds more than 1.5x what it read;
4. a projection to ``--target-km2`` / ``--target-points`` on ``--target-workers`` from the measured bytes,
   requests and seconds per task (``benchmarks/_s3_projection.py`` states its assumptions);
5. the HTTP requests the server logged during the S3 run, per unit run (units from the run's summary);
6. patch reads by byte ranges on the local run's tile stores (as ``objstore_bench.py``).

Both runs do the same work: the same config, stages and worker count, one Prefect API server started here;
only where the bytes live differs. Registration samples by the inputs' source ids (paths vs URLs), so its
result may differ in the last digits.

Usage: ``python benchmarks/s3_campus_bench.py [--campus DIR] [--workers 2] [--mode cluster] [--keep DIR]``
(default campus: the demo campus, generated with ``ms3d synth --preset demo`` when missing).
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import ensure_demo, machine
from benchmarks.objstore_bench import BUCKET, bench_patch_reads, start_server
from storage.objstore.store import open_store

MS3D = [sys.executable, "-m", "flows.cli"]
MiB = 2**20
INPUT_KEYS = ("mesh", "points", "labels", "images", "cameras")


def upload(folder: Path, url: str) -> int:
    """Every file under ``folder`` to ``url``; returns the bytes uploaded."""
    store, total = open_store(url), 0
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            store.put_file(p.relative_to(folder).as_posix(), p)
            total += p.stat().st_size
    return total


def url_inputs(config: Path, base: str) -> list[str]:
    """``--set`` overrides naming every input of ``config`` by its URL under ``base`` (same relative layout)."""
    import json

    import yaml

    doc = yaml.safe_load(config.read_text())
    out = []
    for key in INPUT_KEYS:
        v = (doc.get("inputs") or {}).get(key)
        if v is None:
            continue
        urls = [f"{base}/{Path(p).as_posix().strip('/')}" for p in (v if isinstance(v, list) else [v])]
        out += ["--set", f"inputs.{key}={json.dumps(urls if isinstance(v, list) else urls[0])}"]
    return out


def run(config: Path, work: str, workers: int, extra: list[str], env: dict, cwd: Path | None = None
        ) -> tuple[float, dict, str]:
    """``ms3d run``; returns (wall seconds, {stage: units run}, stdout)."""
    t0 = time.perf_counter()
    p = subprocess.run(MS3D + ["run", str(config), "--work-dir", work, "--workers", str(workers), *extra],
                       capture_output=True, text=True, env=env, cwd=cwd, check=False)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"ms3d run ({work}) failed ({p.returncode}): {(p.stdout + p.stderr).strip()[-3000:]}")
    units = {m[1]: int(m[2]) for m in re.finditer(r"^(\w+): (\d+) run, \d+ unchanged", p.stdout, re.MULTILINE)}
    return wall, units, p.stdout


def recorded_work_dir(url: str, scratch: Path) -> tuple[int, int, dict]:
    """(bytes of the files the work dir's records name, bytes of every object under its prefix, campus.json):
    the records folded without downloading a file but campus.json."""
    import json

    from storage.objstore.mirror import Mirror

    store = open_store(url)
    m = Mirror(store, scratch)
    m.pull(lambda rel: rel == "campus.json")
    live = sum(size for size, _ in m.files.values())
    in_bucket = sum(o.size for o in store.list(""))
    campus = json.loads((m.root / "campus.json").read_text()) if (m.root / "campus.json").exists() else {}
    return live, in_bucket, campus


def campus_extent(campus: dict) -> tuple[float, float]:
    """(area in km² of the inputs' xy bounding box, MLS point count) from campus.json's input records."""
    recs = [r for r in campus.get("inputs", []) if not r.get("error")]
    lo = [min(r["lo"][i] for r in recs) for i in (0, 1)]
    hi = [max(r["hi"][i] for r in recs) for i in (0, 1)]
    points = sum(r.get("count", 0) for r in recs if r.get("kind") == "points")
    return (hi[0] - lo[0]) * (hi[1] - lo[1]) / 1e6, float(points)


def print_processes(title: str, figures: list, work_bytes: int) -> None:
    """The per-process table of ``figures`` (``benchmarks._cluster.ProcessFigures``); shares of ``work_bytes``."""
    print(f"\n{title}")
    print(f"  {'process':<10} {'downloaded MiB':>14} {'of which inputs':>15} {'held on scratch MiB':>19} "
          f"{'requests':>9} {'held/read':>9} {'downloaded / work dir':>21}")
    for f in figures:
        inputs = int(f.doc.get("inputs", {}).get("bytes_read", 0))
        ratio = f"{f.held / f.read_bytes:.2f}" if f.read_bytes else "-"
        print(f"  {f.name:<10} {f.read_bytes / MiB:>14.1f} {inputs / MiB:>15.1f} {f.held / MiB:>19.1f} "
              f"{f.requests:>9,} {ratio:>9} {100 * f.read_bytes / max(work_bytes, 1):>20.2f}%")


def cluster_runs(a, config: Path, prefix: str, root: Path, env: dict, counter) -> dict:
    """The S3 run on a no-shared-disk cluster, then a no-op rerun from a fresh driver; prints the per-process
    tables. Returns the figures the projection and the summary need."""
    from benchmarks._cluster import DaskCluster, ProcessFigures, process_env

    work = prefix + "/work"
    extra = url_inputs(config, prefix + "/inputs")
    with DaskCluster(root / "cluster", a.workers, env) as cluster:
        extra += ["--dask-address", cluster.address]
        driver1, driver2 = root / "cluster" / "driver1", root / "cluster" / "driver2"
        driver1.mkdir()
        driver2.mkdir()
        n0 = counter.n
        s3_s, units, _ = run(config, work, a.workers, extra, process_env(driver1 / "cache", env), driver1)
        requests = counter.n - n0
        workers1 = cluster.figures()
        live, in_bucket, campus = recorded_work_dir(work, root / "recorded")
        d1 = ProcessFigures.read("driver", driver1 / "cache")
        print(f"\nwork dir in the bucket: {live / MiB:,.1f} MiB recorded (the live files), {in_bucket / MiB:,.1f} MiB "
              f"of objects under its prefix; shares below are of the recorded {live / MiB:,.1f} MiB")
        print_processes("first run, per process (cumulative)", d1 + workers1, live)
        n1 = counter.n
        rerun_s, rerun_units, _ = run(config, work, a.workers, extra, process_env(driver2 / "cache", env), driver2)
        rerun_requests = counter.n - n1
        before = {f.name: f for f in workers1}
        workers2 = [f.minus(before.get(f.name)) for f in cluster.figures()]
        d2 = ProcessFigures.read("driver", driver2 / "cache")
        print_processes(f"no-op rerun from a new driver (fresh MS3D_CACHE), {rerun_s:.1f} s, {sum(rerun_units.values())} "
                        f"units run, {rerun_requests:,} requests at the server; workers: what they did during the "
                        "rerun, held: now", d2 + workers2, live)
        d2_read = sum(f.read_bytes for f in d2)
        print(f"  fresh driver's no-op rerun downloaded {100 * d2_read / max(live, 1):.2f} % of the work dir (goal <= 1 %)")
        everyone = d1 + workers1
        worst = max(everyone, key=lambda f: f.held / f.read_bytes if f.read_bytes else 0.0)
        print(f"  largest held/read after the first run: {worst.name} {worst.held / max(worst.read_bytes, 1):.2f} "
              "(goal <= 1.5)")
    return {"wall": s3_s, "units": units, "requests": requests, "campus": campus, "live": live,
            "driver": d1, "rerun_driver": d2, "workers": workers1}


def _driver_figures(figs: list) -> dict:
    return {"read": sum(f.read_bytes for f in figs), "written": sum(f.moved("bytes_written") for f in figs),
            "requests": sum(f.requests for f in figs), "held": sum(f.held for f in figs)}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campus", type=Path, help="a campus folder with campus.yaml (default: the demo campus)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--mode", choices=("cluster", "local-cluster"), default="cluster")
    ap.add_argument("--sample", type=int, default=10, help="patches read per tile")
    ap.add_argument("--keep", type=Path, help="keep the local work dir and the S3 caches here")
    ap.add_argument("--target-km2", type=float, default=2.0)
    ap.add_argument("--target-points", type=float, default=1e10)
    ap.add_argument("--target-workers", type=int, default=16)
    ap.add_argument("--latency-ms", type=float, default=20.0, help="per request, for the projection")
    ap.add_argument("--mbps", type=float, default=200.0, help="MB/s per process, for the projection")
    a = ap.parse_args(argv)
    campus = (a.campus or ensure_demo()).resolve()
    config = campus / "campus.yaml"
    print(f"machine: {machine()}; campus {campus}; {a.workers} workers; mode {a.mode}")
    server, counter = start_server()
    tmp = tempfile.TemporaryDirectory(prefix="ms3d-s3-bench-")
    root = a.keep or Path(tmp.name)
    from flows.runtime import PrefectServer

    prefect = PrefectServer(root / "prefect").start()
    try:
        prefix = f"s3://{BUCKET}/campus-bench"
        t0 = time.perf_counter()
        nbytes = upload(campus, prefix + "/inputs")
        print(f"uploaded the inputs: {nbytes / 2**20:,.0f} MiB in {time.perf_counter() - t0:.0f} s")
        base = {**os.environ, "PREFECT_API_URL": prefect.api_url, "OMP_NUM_THREADS": "1"}
        local_env = {k: v for k, v in base.items() if not k.startswith("AWS_")}
        local_s, local_units, _ = run(config, str(root / "local"), a.workers, [], local_env)
        print(f"local run: {local_s:.1f} s")
        if a.mode == "cluster":
            got = cluster_runs(a, config, prefix, root, base, counter)
            s3_s, s3_units, requests = got["wall"], got["units"], got["requests"]
        else:
            s3_env = {**base, "MS3D_CACHE": str(root / "cache")}
            n0 = counter.n
            s3_s, s3_units, _ = run(config, prefix + "/work", a.workers, url_inputs(config, prefix + "/inputs"),
                                    s3_env)
            requests = counter.n - n0
        n_units = sum(s3_units.values())
        print(f"\n{'work dir':<10} {'wall s':>8} {'units run':>9}  units per stage")
        for name, wall, units in (("local", local_s, local_units), ("S3", s3_s, s3_units)):
            print(f"{name:<10} {wall:>8.1f} {sum(units.values()):>9}  {units}")
        print(f"S3 / local wall: {s3_s / local_s:.2f}x (goal <= 1.3x)")
        print(f"S3 requests during the S3 run: {requests:,} = {requests / max(n_units, 1):.1f} per unit run "
              f"({n_units} units)")
        if a.mode == "cluster":
            from benchmarks._s3_projection import Scale, print_projection

            area, points = campus_extent(got["campus"])
            read = sum(f.read_bytes for f in got["workers"])
            ratio = sum(f.held for f in got["workers"]) / max(read, 1)
            print_projection(Scale(area, points, a.target_km2, a.target_points, a.target_workers,
                                   a.latency_ms / 1e3, a.mbps * 1e6),
                             [f.doc for f in got["workers"]], _driver_figures(got["driver"]),
                             _driver_figures(got["rerun_driver"]), ratio)
        print("\npatch reads by byte ranges (the local run's tile stores, uploaded):")
        bench_patch_reads(open_store(f"s3://{BUCKET}/patch-reads"), root / "local" / "tiles", a.sample)
    finally:
        prefect.stop()
        server.stop()
        if not a.keep:
            tmp.cleanup()


if __name__ == "__main__":
    main()
