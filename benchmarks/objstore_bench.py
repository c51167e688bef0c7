"""The object-store layer on a local S3 server (moto's server mode on 127.0.0.1): what reading one patch
fetches against its tile's file size, and what one unit's commit costs in requests, S3 against local disk.

1. Patch reads by byte ranges: a tile store (built in code, or every tile of ``--work``, an existing work
   dir) is uploaded; for a sample of its patches, :func:`storage.patches.ranges.read_patch_rows` reads one
   patch's points; printed: points.parquet size, bytes fetched (median, max), their ratio, GETs per patch.
2. Requests per unit: ``--units`` cycles of put_unit_outputs (``--files`` outputs of ``--kib`` KiB) +
   resolve + read_output of every output, then one sweep; printed: HTTP requests per unit as counted by
   the server (its request log) and by the store, and seconds per unit on S3 and on local disk.

Usage: ``python benchmarks/objstore_bench.py [--work DIR] [--patches 40] [--per-patch 4000]
[--row-group 4000] [--units 50] [--files 3] [--kib 256]``
"""

from __future__ import annotations

import argparse
import logging
import os
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from storage.grid import PatchGrid
from storage.objstore.commit import put_unit_outputs, read_output, resolve, sweep_unrecorded
from storage.objstore.store import open_store
from storage.patches.ranges import read_patch_index, read_patch_rows
from storage.patches.schema import TileMeta
from storage.patches.write import write_tile_tables
from tasks.partition.kernels import build_tile_tables

BUCKET = "ms3d-bench"


class _RequestCounter(logging.Handler):
    """Counts the HTTP requests moto's server logs (werkzeug's access log)."""

    def __init__(self):
        super().__init__(logging.INFO)
        self.n = 0

    def emit(self, record):
        if "HTTP/1." in record.getMessage():
            self.n += 1


def start_server():
    """moto's S3 server on 127.0.0.1 with one bucket; returns (server, request counter)."""
    import boto3
    from moto.server import ThreadedMotoServer

    counter = _RequestCounter()
    log = logging.getLogger("werkzeug")  # before the first request, or werkzeug adds its stderr handler
    log.setLevel(logging.INFO)
    log.propagate = False
    log.addHandler(counter)
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    assert host == "127.0.0.1"
    os.environ.update(AWS_ENDPOINT_URL=f"http://{host}:{port}", AWS_ACCESS_KEY_ID="bench",
                      AWS_SECRET_ACCESS_KEY="bench-secret", AWS_DEFAULT_REGION="us-east-1")
    boto3.client("s3").create_bucket(Bucket=BUCKET)
    return server, counter


def build_tile(out: Path, n_patches: int, per_patch: int, row_group: int, seed: int = 0) -> Path:
    """One tile store of ``n_patches`` cells in a row along x, ``per_patch`` random points each."""
    size = (2.3, 1.0, 0.7)
    rng = np.random.default_rng(seed)
    cell = np.repeat(np.arange(n_patches), per_patch)
    xyz = rng.random((len(cell), 3)) * [2.2, 0.9, 0.6] + 0.05
    xyz[:, 0] += cell * size[0]
    n = len(cell)
    points = {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
              "z": xyz[:, 2].astype(np.float32), "gps_time": rng.random(n) * 1e3,
              "intensity": rng.integers(0, 65535, n).astype(np.uint16),
              "red": rng.integers(0, 65535, n).astype(np.uint16), "classification": rng.integers(0, 9, n).astype(np.uint8)}
    p, f, patches = build_tile_tables(points, None, PatchGrid(size, 100.0), (0.0, 0.0, 0.0))
    write_tile_tables(out / "0_0", p, f, patches, TileMeta(tile="0_0", patch_size_m=size), row_group_size=row_group)
    return out


def bench_patch_reads(store, tiles_root: Path, sample: int) -> None:
    tiles = sorted(d for d in tiles_root.iterdir() if (d / "patches.parquet").exists())
    for d in tiles:
        for name in ("points.parquet", "faces.parquet", "patches.parquet"):
            if (d / name).exists():
                store.put_file(f"tiles/{d.name}/{name}", d / name)
    print(f"{'tile':>8} {'patches':>7} {'points.parquet':>14} {'fetched median':>14} {'max':>9} "
          f"{'ratio':>7} {'GETs':>5} {'index':>8}")
    for d in tiles:
        index, index_bytes = read_patch_index(store, d.name)
        keys = index["patch"][index["n_points"] > 0]
        if not len(keys):
            continue
        pick = keys[np.linspace(0, len(keys) - 1, min(sample, len(keys))).astype(int)]
        rows = [read_patch_rows(store, d.name, int(k), "points", index=index) for k in pick]
        fetched = [r.bytes_fetched for r in rows]
        med = statistics.median(fetched)
        print(f"{d.name:>8} {len(keys):>7} {rows[0].file_size:>14,} {med:>14,.0f} {max(fetched):>9,} "
              f"{med / rows[0].file_size:>7.3f} {statistics.median(r.requests for r in rows) + 1:>5.0f} "
              f"{index_bytes:>8,}")


def unit_cycle(store, units: int, files: int, kib: int) -> float:
    rng = np.random.default_rng(1)
    payload = {f"out{i}.bin": rng.bytes(kib * 1024) for i in range(files)}
    t0 = time.perf_counter()
    for u in range(units):
        put_unit_outputs(store, "bench", f"u{u}", payload)
        rec = resolve(store, "bench", f"u{u}")
        for name in rec.files:
            read_output(store, rec, name)
    return time.perf_counter() - t0


def bench_units(store, counter, local_root: Path, args) -> None:
    n0, s0 = counter.n, store.stats.n_requests
    s3_s = unit_cycle(store, args.units, args.files, args.kib)
    http, logical = counter.n - n0, store.stats.n_requests - s0
    local_s = unit_cycle(open_store(local_root), args.units, args.files, args.kib)
    n1 = counter.n
    t0 = time.perf_counter()
    swept = sweep_unrecorded(store, grace_s=0)
    sweep_s, sweep_http = time.perf_counter() - t0, counter.n - n1
    print(f"unit = put_unit_outputs of {args.files} x {args.kib} KiB + resolve + read_output of each, "
          f"{args.units} units")
    print(f"  S3 requests per unit: {http / args.units:.1f} by the server's log "
          f"({logical / args.units:.1f} counted by the store)")
    print(f"  seconds per unit: S3 {s3_s / args.units * 1e3:.1f} ms, local disk {local_s / args.units * 1e3:.1f} ms "
          f"({s3_s / max(local_s, 1e-9):.1f}x)")
    print(f"  sweep of {args.units} records: {sweep_http} requests, {sweep_s:.2f} s, {len(swept)} objects deleted")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", type=Path, help="an existing work dir whose tiles/ to upload (default: build one)")
    ap.add_argument("--patches", type=int, default=40)
    ap.add_argument("--per-patch", type=int, default=4000)
    ap.add_argument("--row-group", type=int, default=4000)
    ap.add_argument("--sample", type=int, default=10, help="patches read per tile")
    ap.add_argument("--units", type=int, default=50)
    ap.add_argument("--files", type=int, default=3)
    ap.add_argument("--kib", type=int, default=256)
    args = ap.parse_args(argv)
    server, counter = start_server()
    try:
        with tempfile.TemporaryDirectory() as tmp:
            store = open_store(f"s3://{BUCKET}/{uuid.uuid4().hex[:8]}")
            tiles = args.work / "tiles" if args.work else \
                build_tile(Path(tmp) / "tiles", args.patches, args.per_patch, args.row_group)
            print(f"patch reads by byte ranges ({'work dir ' + str(args.work) if args.work else 'built tile: '}"
                  f"{'' if args.work else f'{args.patches} patches x {args.per_patch} points, row groups of {args.row_group}'})")
            bench_patch_reads(store, tiles, args.sample)
            bench_units(store, counter, Path(tmp) / "local", args)
    finally:
        server.stop()


if __name__ == "__main__":
    main()
