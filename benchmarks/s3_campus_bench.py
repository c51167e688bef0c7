"""A whole campus with its inputs and work dir on S3 (moto's server on 127.0.0.1) against the same campus on
local disk, run side by side: wall time, S3 requests per unit, and what reading one patch fetches.

1. ``ms3d run`` of the campus on local disk (``--workers`` Dask worker processes, embedded Prefect server);
2. the same inputs uploaded to the local S3 server, ``ms3d run`` with ``--work-dir s3://…`` and every input
   by URL (workers stage inputs into ``MS3D_CACHE``, pull/push the work dir around each task); the wall
   time ratio S3 / local is the figure (goal <= 1.3x);
3. the HTTP requests the server logged during the S3 run, per unit run (units from the run's summary);
4. patch reads by byte ranges on the local run's tile stores (as ``objstore_bench.py``).

Both runs do the same work: the same config, stages and worker count; only where the bytes live differs.
Registration samples by the inputs' source ids (paths vs URLs), so its result may differ in the last digits.

Usage: ``python benchmarks/s3_campus_bench.py [--campus DIR] [--workers 2] [--keep DIR]``
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


def run(config: Path, work: str, workers: int, extra: list[str], env: dict) -> tuple[float, dict, str]:
    """``ms3d run``; returns (wall seconds, {stage: units run}, stdout)."""
    t0 = time.perf_counter()
    p = subprocess.run(MS3D + ["run", str(config), "--work-dir", work, "--workers", str(workers), *extra],
                       capture_output=True, text=True, env=env, check=False)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"ms3d run ({work}) failed ({p.returncode}): {p.stderr.strip().splitlines()[-1:]}")
    units = {m[1]: int(m[2]) for m in re.finditer(r"^(\w+): (\d+) run, \d+ unchanged", p.stdout, re.MULTILINE)}
    return wall, units, p.stdout


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campus", type=Path, help="a campus folder with campus.yaml (default: the demo campus)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--sample", type=int, default=10, help="patches read per tile")
    ap.add_argument("--keep", type=Path, help="keep the local work dir and the S3 cache here")
    a = ap.parse_args(argv)
    campus = (a.campus or ensure_demo()).resolve()
    config = campus / "campus.yaml"
    print(f"machine: {machine()}; campus {campus}; {a.workers} workers")
    server, counter = start_server()
    tmp = tempfile.TemporaryDirectory(prefix="ms3d-s3-bench-")
    root = a.keep or Path(tmp.name)
    try:
        prefix = f"s3://{BUCKET}/campus-bench"
        t0 = time.perf_counter()
        nbytes = upload(campus, prefix + "/inputs")
        print(f"uploaded the inputs: {nbytes / 2**20:,.0f} MiB in {time.perf_counter() - t0:.0f} s")
        local_env = {k: v for k, v in os.environ.items() if not k.startswith("AWS_")}
        local_s, local_units, _ = run(config, str(root / "local"), a.workers, [], local_env)
        s3_env = {**os.environ, "MS3D_CACHE": str(root / "cache")}
        n0 = counter.n
        s3_s, s3_units, _ = run(config, prefix + "/work", a.workers, url_inputs(config, prefix + "/inputs"), s3_env)
        requests = counter.n - n0
        n_units = sum(s3_units.values())
        print(f"\n{'work dir':<10} {'wall s':>8} {'units run':>9}  units per stage")
        for name, wall, units in (("local", local_s, local_units), ("S3", s3_s, s3_units)):
            print(f"{name:<10} {wall:>8.1f} {sum(units.values()):>9}  {units}")
        print(f"S3 / local wall: {s3_s / local_s:.2f}x (goal <= 1.3x)")
        print(f"S3 requests during the S3 run: {requests:,} = {requests / max(n_units, 1):.1f} per unit run "
              f"({n_units} units)")
        print("\npatch reads by byte ranges (the local run's tile stores, uploaded):")
        bench_patch_reads(open_store(f"s3://{BUCKET}/patch-reads"), root / "local" / "tiles", a.sample)
    finally:
        server.stop()
        if not a.keep:
            tmp.cleanup()


if __name__ == "__main__":
    main()
