"""COPC bounds queries against reading the whole file: bytes read, octree nodes and points decompressed, time.

Writes a synthetic street-like cloud (``--points`` over ``--side-m`` x ``--side-m`` metres, 1 mm lattice, every
LAS field) as a COPC file with :func:`synth.copc.write_copc`, then reads, in this process, single-threaded:

1. the whole file through the registry's plain LAZ reader (``storage.formats.points.iter_points``);
2. the whole file through :func:`storage.formats.copc.iter_copc`;
3. boxes of one ground tile (``--tile-m``) and of a campus (4 x 4 tiles) at the cloud's centre through
   ``iter_copc``, checked equal to the plain reader's points filtered by the box.

For each read it prints bytes read from the file (header, hierarchy pages, chunks), nodes and points
decompressed, points returned, and CPU seconds. The script always exits 0: it reports.

    .venv/bin/python benchmarks/copc_bench.py                         # 2 M points over 1 km x 1 km
    .venv/bin/python benchmarks/copc_bench.py --points 10000000 --levels 6
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "RAYON_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy / lazrs load: a per-core figure on a shared machine

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from storage.formats.copc import CopcReadStats, iter_copc
from storage.formats.point_chunk import PointChunk
from storage.formats.points import iter_points
from synth.copc import write_copc


def cloud(n: int, side_m: float, seed: int = 0) -> PointChunk:
    """Points on a 1 mm lattice over a side_m square, 30 m of height, sorted by GPS time along x (a drive)."""
    rng = np.random.default_rng(seed)
    mm = rng.integers(0, [int(side_m * 1000), int(side_m * 1000), 30_000], size=(n, 3))
    xyz = np.array([500_000.0, 4_000_000.0, 0.0]) + mm / 1000.0
    order = np.argsort(xyz[:, 0], kind="stable")
    return PointChunk(xyz=xyz[order], rgb=rng.integers(0, 65536, (n, 3)).astype(np.uint16),
                      intensity=rng.integers(0, 65536, n).astype(np.uint16),
                      gps_time=np.linspace(3.0e5, 3.0e5 + n / 1e5, n),
                      classification=rng.integers(0, 20, n).astype(np.uint8))


def cpu() -> float:
    t = os.times()
    return t.user + t.system


def read(label: str, chunks, stats: CopcReadStats | None, size: int) -> PointChunk:
    t0 = cpu()
    got = PointChunk.concat(chunks)
    secs = cpu() - t0
    if stats is None:
        print(f"{label:<34} {'(laspy stream)':>14} {'':>7} {len(got):>12,} {len(got):>12,} {secs:>8.2f}")
    else:
        print(f"{label:<34} {stats.bytes_read:>14,} {stats.nodes_decoded:>7,} {stats.points_decoded:>12,} "
              f"{stats.points_returned:>12,} {secs:>8.2f}   {stats.bytes_read / size:6.1%} of the file")
    return got


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--side-m", type=float, default=1000.0)
    ap.add_argument("--levels", type=int, default=5, help="octree depth (root = 0)")
    ap.add_argument("--span", type=int, default=16, help="cells per node side that thin the coarse levels")
    ap.add_argument("--tile-m", type=float, default=100.0)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "street.copc.laz"
        src = cloud(args.points, args.side_m)
        t0 = time.perf_counter()
        layout = write_copc(path, src, crs="EPSG:32650", max_level=args.levels, span=args.span, page_level=3)
        size = path.stat().st_size
        del src
        print(f"COPC: {args.points:,} points, {len(layout.nodes):,} nodes in {layout.pages} hierarchy pages, "
              f"{size:,} bytes, written in {time.perf_counter() - t0:.1f} s")
        print(f"{'read':<34} {'bytes read':>14} {'nodes':>7} {'decoded':>12} {'returned':>12} {'cpu s':>8}")
        plain = read("whole file, plain LAZ reader", iter_points(path, 1_000_000), None, size)
        stats = CopcReadStats()
        read("whole file, iter_copc", iter_copc(path, 1_000_000, stats=stats), stats, size)
        centre = np.array([500_000.0, 4_000_000.0]) + args.side_m / 2
        for label, half in ((f"one tile ({args.tile_m:.0f} m)", args.tile_m / 2),
                            (f"campus (4 x 4 tiles, {4 * args.tile_m:.0f} m)", 2 * args.tile_m)):
            box = np.array([centre - half, centre + half])
            stats = CopcReadStats()
            got = read(label, iter_copc(path, 1_000_000, bounds=box, stats=stats), stats, size)
            keep = np.all((plain.xyz[:, :2] >= box[0]) & (plain.xyz[:, :2] <= box[1]), axis=1)
            same = len(got) == keep.sum() and np.array_equal(got.xyz, plain.xyz[keep]) and np.array_equal(
                got.gps_time, plain.gps_time[keep]) and np.array_equal(got.rgb, plain.rgb[keep])
            print(f"{'':<34} the plain reader's points in the box: {'identical' if same else 'DIFFERENT'}")


if __name__ == "__main__":
    main()
