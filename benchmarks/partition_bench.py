"""Partition + write throughput per core, and the peak RSS of one tile task, beside a pandas baseline.

Measures, in one run, on the demo campus (``--input DIR``: a ``synth`` output with ``mls/*.laz`` and
``campus.yaml``; the default when ``ms3d-work/demo-input`` exists) or on a synthetic campus written here
(``--synthetic-points N``: N MLS-like points on building walls and ground over 400 x 400 m, UTM 50N
coordinates, plus a gridded mesh of N/8 faces):

1. ms3d: the register and ingest stage functions run once (registration disabled) to stage each tile; then
   per tile ``build_tile_tables`` + ``write_tile_tables`` (partition + write) on the staged columns, for
   points only, faces only and both; then the whole stage ``run_partition_tile`` (read staging too).
2. Baseline, same points, as a user would write it: ``laspy.read`` + a pandas DataFrame, patch ids
   ``floor(xyz / size)``, ``groupby`` per tile, ``sort_values`` by patch, a per-patch ``agg`` table and
   ``to_parquet`` per tile (pandas defaults).
3. Peak RSS of one tile task: ``run_partition_tile`` of tile 1_1 in a fresh process, on two synthetic
   campuses with identical content per 100 m block (4 and 16 tiles; with ``--input``, also the input's
   largest tile); the baseline's peak RSS (whole campus in one DataFrame) beside it.

Everything runs in one process with one thread (OMP/OPENBLAS/MKL/RAYON threads = 1, pyarrow cpu_count 1);
rates "per core" divide by CPU seconds (user + system of the process), which other jobs on a shared
machine inflate far less than wall seconds (printed beside them, with the load average). The script always exits 0: it reports.

    .venv/bin/python benchmarks/partition_bench.py                       # demo campus if made, else 20 M
    .venv/bin/python benchmarks/partition_bench.py --synthetic-points 20000000 --work /tmp/pbench
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "RAYON_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy/laspy import; inherited by the child processes

import argparse
import json
import logging
import platform
import resource
import shutil
import subprocess
import sys
import tempfile
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

WORLD_ORIGIN = (589_000.0, 2_712_000.0, 15.0)  # UTM 50N metres, a multiple of 100 m: tiles = blocks
CRS = "EPSG:32650"
BLOCK_M = 100.0  # one synthetic block per default 100 m tile
RSS_TILE = f"{int(WORLD_ORIGIN[0] // 100) + 1}_{int(WORLD_ORIGIN[1] // 100) + 1}"  # the second block of both campuses
TARGET_POINTS_PER_S = 3e6


@dataclass
class Timing:
    wall: float = 0.0
    cpu: float = 0.0

    def add(self, other: Timing) -> None:
        self.wall += other.wall
        self.cpu += other.cpu


class timed:
    """``with timed(t):`` adds the block's wall and process CPU seconds to the Timing ``t``."""

    def __init__(self, into: Timing):
        self.into = into

    def __enter__(self):
        self.w, self.c = time.perf_counter(), time.process_time()

    def __exit__(self, *exc):
        self.into.add(Timing(time.perf_counter() - self.w, time.process_time() - self.c))


def _single_thread_arrow() -> None:
    import pyarrow as pa

    pa.set_cpu_count(1)
    pa.set_io_thread_count(1)


def _peak_rss_bytes() -> int:
    """Peak RSS of this process image. /proc VmHWM, not getrusage: a child's ru_maxrss keeps the parent's
    RSS at fork time across exec, so it would report the benchmark's own footprint."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # not Linux: KiB on Linux, bytes on macOS


def _rss_bytes() -> int:
    import psutil

    return psutil.Process().memory_info().rss


# ----------------------------------------------------------------------------------- synthetic inputs


def _grid(p0, du, dv, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A planar grid of 2*nu*nv triangles spanning p0 + [0, 1] du + [0, 1] dv: (vertices, faces)."""
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = np.asarray(p0) + s.reshape(-1, 1) * np.asarray(du) + t.reshape(-1, 1) * np.asarray(dv)
    a = (np.arange(nu)[:, None] * (nv + 1) + np.arange(nv)[None, :]).reshape(-1)
    b, c, d = a + nv + 1, a + 1, a + nv + 2
    return verts, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def _block_buildings(rng: np.random.Generator, x0: float, y0: float) -> np.ndarray:
    """(b, 5) float64 boxes [x, y, width, depth, height] metres inside the block at (x0, y0)."""
    n = int(rng.integers(3, 6))
    w, d, h = rng.uniform(12, 35, n), rng.uniform(10, 25, n), rng.uniform(6, 40, n)
    x = x0 + 5 + rng.uniform(0, 1, n) * (BLOCK_M - 10 - w)
    y = y0 + 5 + rng.uniform(0, 1, n) * (BLOCK_M - 10 - d)
    return np.stack([x, y, w, d, h], 1)


def synthetic_block(seed: int, bx: int, by: int, n_points: int, n_faces: int):
    """Block (bx, by): MLS-like points (65 % on building walls, 35 % on the ground) and a gridded mesh of
    ground, walls and roofs, in campus-local metres; deterministic from (seed, bx, by) alone.

    Returns (xyz (n, 3) float64, attrs dict of (n,) arrays, vertices (v, 3) float64, faces (m, 3) int64).
    """
    rng = np.random.default_rng([seed, bx, by])
    x0, y0 = bx * BLOCK_M, by * BLOCK_M
    b = _block_buildings(rng, x0, y0)
    corners = np.stack([b[:, :2], b[:, :2] + b[:, [2]] * [1, 0], b[:, :2] + b[:, 2:4], b[:, :2] + b[:, [3]] * [0, 1]], 1)
    p0, p1 = corners.reshape(-1, 2), np.roll(corners, -1, axis=1).reshape(-1, 2)
    wall_h = np.repeat(b[:, 4], 4)
    length = np.linalg.norm(p1 - p0, axis=1)
    n_wall = int(n_points * 0.65)
    wall = rng.choice(len(p0), n_wall, p=length * wall_h / (length * wall_h).sum())
    t = rng.random(n_wall)[:, None]
    xy_wall = p0[wall] + t * (p1[wall] - p0[wall]) + rng.normal(0, 0.005, (n_wall, 2))
    xy_ground = [x0, y0] + rng.random((n_points - n_wall, 2)) * (BLOCK_M - 0.01)  # LAS rounding stays inside
    xyz = np.empty((n_points, 3))
    xyz[:n_wall, :2], xyz[:n_wall, 2] = xy_wall, rng.random(n_wall) * wall_h[wall]
    xyz[n_wall:, :2], xyz[n_wall:, 2] = xy_ground, rng.normal(0, 0.01, n_points - n_wall)
    attrs = {"intensity": rng.integers(0, 4096, n_points).astype(np.uint16),
             "gps_time": 302_400.0 + (bx * 64 + by) * 600.0 + np.sort(rng.random(n_points)) * 600.0,
             "rgb": rng.integers(0, 65535, (n_points, 3)).astype(np.uint16),
             "classification": np.where(np.arange(n_points) < n_wall, 6, 2).astype(np.uint8)}
    area = BLOCK_M**2 + (length * wall_h).sum() + (b[:, 2] * b[:, 3]).sum()
    edge = np.sqrt(2 * area / max(n_faces, 1))
    cells = lambda length_m: max(1, round(length_m / edge))
    parts = [_grid([x0, y0, 0], [BLOCK_M, 0, 0], [0, BLOCK_M, 0], cells(BLOCK_M), cells(BLOCK_M))]
    for a, c, h in zip(p0, p1, wall_h):
        parts.append(_grid([*a, 0], [*(c - a), 0], [0, 0, h], cells(np.linalg.norm(c - a)), cells(h)))
    for x, y, w, d, h in b:
        parts.append(_grid([x, y, h], [w, 0, 0], [0, d, 0], cells(w), cells(d)))
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    verts = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    return xyz, attrs, verts, faces


def write_synthetic_campus(out: Path, blocks: int, points_per_block: int, faces_per_block: int, seed: int) -> Path:
    """A blocks x blocks campus: ``mls/strip_{bx}.laz`` (one per block column) and ``mesh/block_{bx}_{by}.ply``.

    Reused when ``out/inputs.json`` says it was written with the same parameters.
    """
    from storage.mesh_io import write_ply
    from storage.pointcloud_io import LasChunkWriter, PointChunk

    params = {"blocks": blocks, "points_per_block": points_per_block, "faces_per_block": faces_per_block,
              "seed": seed, "version": 2}
    stamp = out / "inputs.json"
    if stamp.exists() and json.loads(stamp.read_text()) == params:
        return out
    shutil.rmtree(out, ignore_errors=True)
    (out / "mls").mkdir(parents=True)
    (out / "mesh").mkdir()
    origin = np.asarray(WORLD_ORIGIN)
    for bx in range(blocks):
        with LasChunkWriter(out / "mls" / f"strip_{bx:02d}.laz", crs=CRS, offset=origin.round(-3)) as w:
            for by in range(blocks):
                xyz, a, verts, faces = synthetic_block(seed, bx, by, points_per_block, faces_per_block)
                w.write(PointChunk(xyz=xyz + origin, rgb=a["rgb"], intensity=a["intensity"],
                                   gps_time=a["gps_time"], classification=a["classification"]))
                write_ply(out / "mesh" / f"block_{bx:02d}_{by:02d}.ply", verts + origin, faces)
    stamp.write_text(json.dumps(params))
    return out


def synthetic_config(inputs: Path, work: Path):
    from tasks.config import CampusConfig

    return CampusConfig.model_validate({
        "name": inputs.name, "work_dir": str(work),
        "inputs": {"mesh": [str(inputs / "mesh")], "points": [str(inputs / "mls")]},
        "registration": {"enabled": False}})


# ----------------------------------------------------------------------------------- ms3d stages


def stage_campus(cfg) -> dict:
    """Fresh work dir -> scan -> register (off) -> ingest every unit. Returns counts, timings, frame."""
    from flows.campus import InlineExecutor, scan_inputs
    from storage.workdir import WorkDir
    from tasks.ingest import plan_units, run_ingest_unit
    from tasks.register_stage import run_register

    wd = WorkDir(cfg.work_dir)
    shutil.rmtree(wd.root, ignore_errors=True)
    wd.root.mkdir(parents=True)
    records, frame, *_ = scan_inputs(cfg, wd, InlineExecutor())
    reg = run_register(records, frame, cfg, wd)
    matrix = np.asarray(reg["matrix"], np.float64)
    ingest_pts, ingest_mesh = Timing(), Timing()
    n_points = 0
    for unit in plan_units(records, cfg.tiling.chunk_points):
        with timed(ingest_pts if unit.kind == "points" else ingest_mesh):
            summary = run_ingest_unit(unit, cfg, wd, frame, matrix if unit.kind == "points" else None)
        n_points += summary["rows"] if unit.kind == "points" else 0
    return {"wd": wd, "frame": frame, "register": reg.get("method", "?"), "ingest_points": ingest_pts,
            "ingest_mesh": ingest_mesh, "n_points": n_points, "tiles": wd.staged_tiles()}


def load_staged_tile(wd, tile) -> tuple[dict | None, dict | None, list]:
    """A tile's staging files as the partition stage reads them: (points, faces, textures)."""
    from tasks.ingest import staged_files
    from tasks.patches import load_staged_tile as load

    return load(staged_files(wd, tile.key))


def measure_partition_write(cfg, staged: dict) -> dict:
    """Per tile: build_tile_tables + write_tile_tables for points only, faces only and both; then the
    whole ``run_partition_tile`` stage on every tile."""
    from storage.patch_store import TileMeta, write_tile_tables
    from tasks.partition import build_tile_tables
    from tasks.patches import run_partition_tile

    wd, size, frame = staged["wd"], cfg.partition.patch_size_m, staged["frame"]
    t = {k: Timing() for k in ("points", "faces", "both", "stage")}
    n_pts = n_faces = 0
    scratch = wd.root / "bench-out"
    for tile in staged["tiles"]:
        points, faces, textures = load_staged_tile(wd, tile)
        meta = TileMeta(tile=tile.key, patch_size_m=tuple(size), crs=frame.crs,
                        textures=tuple(textures))
        n_pts += len(points["x"]) if points else 0
        n_faces += len(faces["x0"]) if faces else 0
        for key, p, f in (("points", points, None), ("faces", None, faces), ("both", points, faces)):
            if p is None and f is None:
                continue
            with timed(t[key]):
                ps, fs, patches = build_tile_tables(p, f, cfg.grid(), frame.origin)
                write_tile_tables(scratch / tile.key, ps or None, fs or None, patches, meta)
            del ps, fs, patches
            shutil.rmtree(scratch / tile.key)
        del points, faces
    for tile in staged["tiles"]:
        with timed(t["stage"]):
            run_partition_tile(tile, cfg, wd, frame)
    return {"timings": t, "n_points": n_pts, "n_faces": n_faces}


# ----------------------------------------------------------------------------------- baseline


def baseline_pandas(laz_files: list[str], origin, patch_size, tile_size_m: float, out: Path) -> dict:
    """The straightforward way: laspy + pandas groupby + to_parquet per tile (points only)."""
    import laspy
    import pandas as pd

    t_read, t_pw = Timing(), Timing()
    with timed(t_read):
        frames = []
        for f in laz_files:
            las = laspy.read(f)
            frames.append(pd.DataFrame({
                "x": (np.asarray(las.x) - origin[0]).astype(np.float32),
                "y": (np.asarray(las.y) - origin[1]).astype(np.float32),
                "z": (np.asarray(las.z) - origin[2]).astype(np.float32),
                "intensity": np.asarray(las.intensity), "gps_time": np.asarray(las.gps_time),
                "red": np.asarray(las.red), "green": np.asarray(las.green), "blue": np.asarray(las.blue),
                "classification": np.asarray(las.classification)}))
        df = pd.concat(frames, ignore_index=True)
        del frames, las
    sx, sy, sz = patch_size
    with timed(t_pw):
        df["i"] = np.floor(df["x"] / sx).astype("int32")
        df["j"] = np.floor(df["y"] / sy).astype("int32")
        df["k"] = np.floor(df["z"] / sz).astype("int32")
        df["tx"] = np.floor((df["i"] + 0.5) * sx / tile_size_m).astype("int32")  # tile of the patch centre
        df["ty"] = np.floor((df["j"] + 0.5) * sy / tile_size_m).astype("int32")
        for (tx, ty), g in df.groupby(["tx", "ty"]):
            g = g.drop(columns=["tx", "ty"]).sort_values(["i", "j", "k"], kind="stable")
            patches = g.groupby(["i", "j", "k"]).agg(
                n_points=("x", "size"), xmin=("x", "min"), ymin=("y", "min"), zmin=("z", "min"),
                xmax=("x", "max"), ymax=("y", "max"), zmax=("z", "max")).reset_index()
            d = out / f"{tx}_{ty}"
            d.mkdir(parents=True, exist_ok=True)
            g.to_parquet(d / "points.parquet", index=False)
            patches.to_parquet(d / "patches.parquet", index=False)
    return {"n_points": len(df), "read": t_read, "partition_write": t_pw}


# ----------------------------------------------------------------------------------- child processes


def _child(spec: dict) -> dict:
    """Run one measured job in this fresh process; returns its figures and peak RSS."""
    _single_thread_arrow()
    if spec["kind"] == "tile":
        import importlib

        from storage.frame import CampusFrame
        from storage.ids import TileId
        from storage.workdir import WorkDir
        from tasks.config import CampusConfig
        from tasks.patches import run_partition_tile

        for lazy in ("storage.labels", "storage.patch_store"):  # imported by the stage; load before RSS
            importlib.import_module(lazy)
        wd, tile = WorkDir(spec["wd"]), TileId.from_key(spec["tile"])
        (wd.manifest_dir / "partition" / f"{tile.key}.json").unlink(missing_ok=True)  # force a re-run
        shutil.rmtree(wd.tile_dir(tile), ignore_errors=True)
        rss0 = _rss_bytes()
        t = Timing()
        with timed(t):
            summary = run_partition_tile(tile, CampusConfig.model_validate(spec["cfg"]), wd,
                                         CampusFrame.from_json(spec["frame"]))
        return {"rss_imports": rss0, "peak_rss": _peak_rss_bytes(), "wall": t.wall, "cpu": t.cpu,
                "n_points": summary.get("n_points", 0), "n_faces": summary.get("n_faces", 0)}
    import laspy  # noqa: F401 - imported before the RSS reading, like the tile task's modules
    import pandas  # noqa: F401

    rss0 = _rss_bytes()
    out = Path(spec["out"])
    r = baseline_pandas(spec["laz"], spec["origin"], spec["patch_size"], spec["tile_size_m"], out)
    shutil.rmtree(out, ignore_errors=True)
    return {"rss_imports": rss0, "peak_rss": _peak_rss_bytes(), "n_points": r["n_points"],
            "read": vars(r["read"]), "partition_write": vars(r["partition_write"])}


def run_child(spec: dict) -> dict:
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec)],
                          check=False, capture_output=True, text=True, cwd=REPO)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("RESULT ")]
    if proc.returncode or not lines:
        raise RuntimeError(f"child {spec['kind']} failed (exit {proc.returncode}): {proc.stderr[-2000:]}")
    return json.loads(lines[-1][len("RESULT "):])


def baseline_spec(cfg, staged: dict, out: Path) -> dict:
    from storage.inputs import discover

    return {"kind": "baseline", "laz": list(discover(cfg.inputs.mesh, cfg.inputs.points).points),
            "origin": list(staged["frame"].origin), "patch_size": list(cfg.partition.patch_size_m),
            "tile_size_m": cfg.tiling.tile_size_m, "out": str(out)}


# ----------------------------------------------------------------------------------- report


def machine() -> dict:
    model = next((ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                  if ln.startswith("model name")), platform.processor())
    import pandas
    import pyarrow

    return {"cpu": model, "nproc": os.cpu_count(), "load_avg": os.getloadavg()[0],
            "python": platform.python_version(), "numpy": np.__version__, "pyarrow": pyarrow.__version__,
            "pandas": pandas.__version__}


def _rate(n: int, seconds: float) -> float:
    return n / seconds / 1e6 if n and seconds > 0 else float("nan")


def print_report(r: dict) -> None:
    m = r["machine"]
    print(f"\nms3d partition benchmark: {r['campus']}")
    print(f"machine: {m['cpu']}, nproc {m['nproc']}, load average {m['load_avg']:.2f} at start; python "
          f"{m['python']}, numpy {m['numpy']}, pyarrow {m['pyarrow']}, pandas {m['pandas']}")
    print("one process, one thread (OMP/OPENBLAS/MKL/RAYON threads = 1, pyarrow cpu_count 1); "
          "per core = rows / CPU s")
    print(f"campus.json by: {r['register']}\n")
    print(f"{'step':<58}{'points':>12}{'faces':>11}{'wall s':>9}{'CPU s':>8}{'Mpts/s/core':>13}{'Mfaces/s/core':>15}")
    for name, n_p, n_f, t in r["rows"]:
        print(f"{name:<58}{n_p:>12,}{n_f:>11,}{t.wall:>9.2f}{t.cpu:>8.2f}"
              f"{_rate(n_p, t.cpu):>13.2f}{_rate(n_f, t.cpu):>15.2f}")
    print("(rows with points and faces: both rates use the same seconds)\n")
    for line in r["summary"]:
        print(line)
    if r.get("rss"):
        print("\npeak RSS of one tile task: run_partition_tile of one tile in a fresh process; the baseline "
              "(whole campus) beside it")
        print(f"{'campus':<28}{'tile':>6}{'tiles':>6}{'campus pts':>13}{'tile pts':>11}{'tile faces':>11}"
              f"{'RSS imports':>13}{'peak RSS':>10}{'peak-imp':>10}{'baseline peak':>15}")
        for row in r["rss"]:
            mb = lambda b: f"{b / 2**20:,.0f} MB"
            print(f"{row['campus'][-28:]:<28}{row['tile']:>6}{row['tiles']:>6}{row['campus_points']:>13,}{row['n_points']:>11,}"
                  f"{row['n_faces']:>11,}{mb(row['rss_imports']):>13}{mb(row['peak_rss']):>10}"
                  f"{mb(row['peak_rss'] - row['rss_imports']):>10}{mb(row['baseline_peak_rss']):>15}")
        for line in r["rss_summary"]:
            print(line)
    for err in r["errors"]:
        print(f"\nFAILED {err}")


def throughput_section(cfg, staged: dict, r: dict) -> None:
    pw = measure_partition_write(cfg, staged)
    base = run_child(baseline_spec(cfg, staged, staged["wd"].root / "baseline-out"))
    r["baseline_runs"][str(staged["wd"].root)] = base  # its peak RSS serves the RSS table too
    t, n_p, n_f = pw["timings"], pw["n_points"], pw["n_faces"]
    b_read, b_pw = Timing(**base["read"]), Timing(**base["partition_write"])
    b_total = Timing(b_read.wall + b_pw.wall, b_read.cpu + b_pw.cpu)
    ms3d_e2e = Timing(staged["ingest_points"].wall + t["stage"].wall, staged["ingest_points"].cpu + t["stage"].cpu)
    r["rows"] = [
        ("ms3d  partition + write, points only", n_p, 0, t["points"]),
        ("ms3d  partition + write, faces only", 0, n_f, t["faces"]),
        ("ms3d  partition + write, points + faces", n_p, n_f, t["both"]),
        ("ms3d  run_partition_tile (read staging + partition + write)", n_p, n_f, t["stage"]),
        ("ms3d  ingest points (LAZ decode -> staging per tile)", staged["n_points"], 0, staged["ingest_points"]),
        ("base  pandas ids + groupby + sort + to_parquet (points)", base["n_points"], 0, b_pw),
        ("base  laspy.read + DataFrame", base["n_points"], 0, b_read),
        ("base  total (LAZ -> per-tile Parquet)", base["n_points"], 0, b_total),
        ("ms3d  total points (ingest + run_partition_tile)", n_p, n_f, ms3d_e2e),
    ]
    rate = _rate(n_p, t["points"].cpu)
    r["figures"] = {"ms3d_pw_points_per_s": rate * 1e6, "ms3d_pw_faces_per_s": _rate(n_f, t["faces"].cpu) * 1e6,
                    "ms3d_stage_points_per_s": _rate(n_p, t["stage"].cpu) * 1e6,
                    "baseline_pw_points_per_s": _rate(base["n_points"], b_pw.cpu) * 1e6,
                    "n_points": n_p, "n_faces": n_f, "baseline_n_points": base["n_points"]}
    f = r["figures"]
    r["summary"] = [
        ("ratio ms3d / baseline, partition + write of the points: "
         f"{f['ms3d_pw_points_per_s'] / f['baseline_pw_points_per_s']:.1f}x"),
        ("ratio ms3d / baseline, LAZ -> per-tile Parquet (ms3d also partitions and writes the faces): "
         f"{_rate(n_p, ms3d_e2e.cpu) / _rate(base['n_points'], b_total.cpu):.1f}x"),
        f"same points: ms3d {n_p:,}, baseline {base['n_points']:,}",
        (f"target >= {TARGET_POINTS_PER_S / 1e6:.0f} M points/s per core for partition + write: "
         f"{'MET' if rate * 1e6 >= TARGET_POINTS_PER_S else 'NOT MET'} ({rate:.2f} M/s per CPU second; "
         f"{_rate(n_p, t['points'].wall):.2f} M/s per wall second)"),
    ]


def rss_section(campuses: list[tuple[str, object, dict]], r: dict) -> None:
    rows = []
    for label, cfg, staged in campuses:
        synthetic = label.startswith("synthetic") and any(t.key == RSS_TILE for t in staged["tiles"])
        tile = RSS_TILE if synthetic else max(  # else the largest staged tile
            staged["tiles"], key=lambda t: sum(p.stat().st_size for p in staged["wd"].staging_dir(t).iterdir())).key
        spec = {"kind": "tile", "wd": str(staged["wd"].root), "tile": tile, "cfg": cfg.model_dump(mode="json"),
                "frame": staged["frame"].to_json()}
        row = run_child(spec) | {"campus": label, "tiles": len(staged["tiles"]), "tile": tile,
                                 "campus_points": staged["n_points"]}
        base = r["baseline_runs"].get(str(staged["wd"].root)) or run_child(
            baseline_spec(cfg, staged, staged["wd"].root / "baseline-rss"))
        rows.append(row | {"baseline_peak_rss": base["peak_rss"]})
    r["rss"] = rows
    if len(rows) >= 2:
        a, b = rows[-2], rows[-1]
        grow = (b["peak_rss"] - b["rss_imports"]) / max(a["peak_rss"] - a["rss_imports"], 1)
        per_point = (b["peak_rss"] - b["rss_imports"]) / max(b["n_points"], 1)
        r["rss_summary"] = [
            (f"campus x{b['campus_points'] / a['campus_points']:.1f} points: tile task peak (above imports) "
             f"x{grow:.2f}, baseline peak x{b['baseline_peak_rss'] / a['baseline_peak_rss']:.2f}"),
            (f"peak RSS per worker bounded by the tile size, not the campus size: {'YES' if grow < 1.5 else 'NO'} "
             f"({per_point:.0f} bytes per tile point above imports)")]
    else:
        r["rss_summary"] = []


def synthetic_campus(work: Path, blocks: int, per_block: int, seed: int):
    n_faces = max(per_block // 8, 200)
    inputs = write_synthetic_campus(work / f"inputs-{blocks}x{blocks}-{per_block}-s{seed}", blocks, per_block,
                                    n_faces, seed)
    cfg = synthetic_config(inputs, work / f"wd-{blocks}x{blocks}")
    label = f"synthetic {blocks * BLOCK_M:.0f} x {blocks * BLOCK_M:.0f} m"
    return label, cfg, stage_campus(cfg)


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark, print the report, return the figures (see ``print_report``)."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--input", type=Path, help="a synth output folder with mls/*.laz and campus.yaml")
    ap.add_argument("--synthetic-points", type=int, help="synthetic campus of N points over 400 x 400 m")
    ap.add_argument("--rss-points", type=int, help="points of the 16-tile campus of the RSS check "
                                                   "(default: --synthetic-points, or 8 M with --input)")
    ap.add_argument("--work", type=Path, help="scratch folder, kept (synthetic inputs are reused); default: temp")
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print("RESULT " + json.dumps(_child(json.loads(args.child))))
        return {}
    _single_thread_arrow()
    # registration is off; its co-registration check compares points to the (coarse) mesh vertices and warns
    logging.getLogger("ms3d.ingest").setLevel(logging.ERROR)
    demo = REPO / "ms3d-work" / "demo-input"
    if args.input is None and args.synthetic_points is None and (demo / "campus.yaml").exists():
        args.input = demo
    n_synth = args.synthetic_points or 20_000_000
    work = args.work.absolute() if args.work else Path(tempfile.mkdtemp(prefix="partition-bench-"))
    r = {"machine": machine(), "rows": [], "summary": [], "errors": [], "register": "", "figures": {},
         "baseline_runs": {}}
    try:
        if args.input is not None:
            from tasks.config import CampusConfig

            cfg = CampusConfig.from_yaml(args.input / "campus.yaml", overrides={
                "work_dir": str(work / "wd-input"), "registration.enabled": False})
            staged, campuses = stage_campus(cfg), []
            r["campus"] = f"{args.input} ({len(staged['tiles'])} tiles of {cfg.tiling.tile_size_m:.0f} m)"
            n_rss = args.rss_points or 8_000_000
        else:
            campuses = [synthetic_campus(work, 4, n_synth // 16, args.seed)]
            cfg, staged = campuses[0][1], campuses[0][2]
            r["campus"] = f"{campuses[0][0]}, {len(staged['tiles'])} tiles of {cfg.tiling.tile_size_m:.0f} m"
            n_rss = args.rss_points or n_synth
        r["register"] = staged["register"]
        try:
            throughput_section(cfg, staged, r)
        except Exception:  # noqa: BLE001 - report what failed, keep the other sections
            r["errors"].append("throughput: " + traceback.format_exc())
        try:
            if n_rss != n_synth or args.input is not None or not campuses:
                campuses = [synthetic_campus(work, 4, n_rss // 16, args.seed)]
            campuses.insert(0, synthetic_campus(work, 2, n_rss // 16, args.seed))
            if args.input is not None:
                campuses.insert(0, (str(args.input), cfg, staged))
            rss_section(campuses, r)
        except Exception:  # noqa: BLE001
            r["errors"].append("peak RSS: " + traceback.format_exc())
    except Exception:  # noqa: BLE001
        r["errors"].append("set-up: " + traceback.format_exc())
    finally:
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
        else:
            for wd in work.glob("wd-*"):
                shutil.rmtree(wd, ignore_errors=True)  # keep the (reusable) inputs only
    r.setdefault("campus", "(set-up failed)")
    print_report(r)
    return r


if __name__ == "__main__":
    main()
    sys.exit(0)
