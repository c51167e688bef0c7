"""Merge + export throughput and the peak RSS of merge at two campus sizes, on a processed work dir.

Input: a work dir the campus flow has processed (tile stores, labels; default ``ms3d-work/demo``, which
``make demo`` writes). It is only read: the benchmark links (or copies) its stores into ``--bench``.
Each step runs in a fresh process, so its peak RSS (VmHWM) is its own:

1. merge every live tile (``tasks.merge.stage.run_merge_tile``, one after the other, as one Dask worker would);
2. ``run_export`` on the merged tiles (uncompressed, one process);
3. the same two on a campus ``--replicate`` times larger: the stores copied side by side along y
   (re-partitioned at the shifted place, vertex ids kept unique, labels carried over), so the
   content per tile is the same and only the campus grows.

Printed: triangles per second of merge, of export and of merge + export (leaf triangles / the sum of
the two wall times; and per CPU second), peak RSS of each step at both sizes. Targets:
>= 40 k triangles/s for merge + export on this 2-core machine; peak RSS < 2 GB, not growing with the
campus. Always exits 0: it reports.

    .venv/bin/python benchmarks/output_bench.py                                # ms3d-work/demo
    .venv/bin/python benchmarks/output_bench.py --work-dir W --bench /tmp/ob --replicate 3 --no-export
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

TARGET_TRIANGLES_PER_S = 40_000
RSS_BUDGET_MB = 2048
STORE_FILES = ("points.parquet", "faces.parquet", "patches.parquet", "labels.parquet", "grades.parquet")


def _vm_hwm_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _config(work: Path):
    from storage.workdir.layout import WorkDir, read_campus
    from tasks.config import CampusConfig

    doc = read_campus(WorkDir(work))
    return CampusConfig.model_validate({**doc["config"], "work_dir": str(work)})


def _merge_one(work: str, key: str) -> tuple[dict | None, float]:
    """Merge one tile (in a pool worker); returns its summary and the worker's peak RSS so far."""
    from storage.ids import TileId
    from storage.workdir.layout import WorkDir
    from tasks.merge import run_merge_tile

    return run_merge_tile(TileId.from_key(key), _config(Path(work)), WorkDir(work)), _vm_hwm_mb()


def _child_merge(work: str, processes: int = 1) -> dict:
    """Merge every live tile: one after the other in this process, or over a pool of ``processes``
    (largest tiles first, as Dask workers would take them)."""
    from storage.workdir.layout import WorkDir

    wd = WorkDir(work)
    keys = sorted((t.key for t in wd.live_tiles()), key=lambda k: -(wd.root / "tiles" / k / "faces.parquet").stat().st_size)
    t0, c0 = time.perf_counter(), time.process_time()
    if processes <= 1:
        runs = [_merge_one(work, k)[0] for k in keys]
        peak = _vm_hwm_mb()  # since the last unit began: run_unit resets the peak per unit (max taken below)
    else:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        ctx = multiprocessing.get_context("forkserver")
        with ProcessPoolExecutor(max_workers=processes, mp_context=ctx) as pool:
            got = list(pool.map(_merge_one, [work] * len(keys), keys))
        runs, peak = [r for r, _ in got], max(p for _, p in got)
    wall = time.perf_counter() - t0
    done = [r for r in runs if r and r["status"] == "done"]
    failed = [r["error"] for r in runs if r and r["status"] == "failed"]
    cpu = time.process_time() - c0 if processes <= 1 else sum(r["seconds"] for r in done)  # pool: tile seconds
    peak = max([peak] + [r["peak_rss_mb"] for r in done if math.isfinite(r.get("peak_rss_mb", math.nan))])
    return {"tiles": len(done), "faces": sum(r["faces"] for r in done), "wall_s": wall, "cpu_s": cpu,
            "peak_rss_mb": peak, "failed": failed, "processes": processes,
            "slowest_tile_s": max((r["seconds"] for r in done), default=0.0),
            "largest_tile_faces": max((r["faces"] for r in done), default=0)}  # fmt: skip


def _child_export(work: str, processes: int = 1) -> dict:
    from tasks.config import ExportConfig
    from tasks.export import run_export

    t0, c0 = time.perf_counter(), time.process_time()
    s = run_export(work, ExportConfig(compression="none"), workers=processes)
    return {"tiles": s["tiles"], "faces": s["leaf_faces"], "bytes": s["bytes"], "wall_s": time.perf_counter() - t0,
            "cpu_s": time.process_time() - c0, "peak_rss_mb": _vm_hwm_mb(), "processes": processes}


def _run_child(step: str, work: Path, processes: int = 1) -> dict:
    run = subprocess.run([sys.executable, __file__, "--child", step, str(work), str(processes)], capture_output=True,
                         text=True, cwd=REPO, check=False)  # fmt: skip
    if run.returncode != 0:
        raise RuntimeError(f"{step} on {work} failed:\n{run.stderr[-3000:]}")
    return json.loads(run.stdout.strip().splitlines()[-1])


def link_stores(src: Path, dst: Path) -> Path:
    """A work dir at ``dst`` with src's campus.json and tile stores (hard links where possible)."""
    if dst.exists():
        shutil.rmtree(dst)
    (dst / "tiles").mkdir(parents=True)
    for name in ("campus.json", "registration.json"):
        if (src / name).exists():
            shutil.copy2(src / name, dst / name)
    for d in sorted((src / "tiles").iterdir()):
        if not (d / "patches.parquet").exists() or (d / "stale.json").exists():
            continue
        (dst / "tiles" / d.name).mkdir()
        for f in STORE_FILES:
            if (d / f).exists():
                try:
                    os.link(d / f, dst / "tiles" / d.name / f)
                except OSError:
                    shutil.copy2(d / f, dst / "tiles" / d.name / f)
    return dst


def replicate_stores(src: Path, dst: Path, times: int) -> Path:
    """A campus ``times`` as long: src's stores, then copies shifted north by the campus's span of tiles,
    re-partitioned at their new place (faces only; vertex ids offset per copy; labels carried over)."""
    import numpy as np

    from storage.patches.read import PatchStore
    from storage.patches.schema import FACE_DTYPES, TileMeta
    from storage.patches.write import write_side_table, write_tile_tables
    from storage.workdir.layout import WorkDir, campus_frame, read_campus
    from tasks.partition.kernels import build_tile_tables

    link_stores(src, dst)
    cfg = _config(dst)
    grid, origin = cfg.grid(), campus_frame(read_campus(WorkDir(dst))).origin_array
    keys = sorted(p.name for p in (dst / "tiles").iterdir())
    iy = [int(k.split("_")[1]) for k in keys]
    span_m = (max(iy) - min(iy) + 1) * grid.tile_size_m
    for r in range(1, times):
        for k in keys:
            store = PatchStore(src / "tiles" / k)
            _, faces = store.read_all(point_columns=[], face_columns=list(FACE_DTYPES))
            faces = {c: v for c, v in faces.items() if c not in ("patch", "vp0", "vp1", "vp2")}
            for v in range(3):  # copy r's vertex ids: source id (high 32 bits) moved by r * 2**27, mod 2**31
                faces[f"y{v}"] = (faces[f"y{v}"].astype(np.float64) + r * span_m).astype(np.float32)
                vid = faces[f"vid{v}"]
                moved = (((vid >> 32) + r * (1 << 27)) % (1 << 31) << 32) | (vid & 0xFFFFFFFF)
                faces[f"vid{v}"] = np.where(vid >= 0, moved, -1)
            labels = store.side("labels")
            _, f_sorted, patches = build_tile_tables(None, faces, grid, origin)
            new_key = f"{k.split('_')[0]}_{int(k.split('_')[1]) + r * round(span_m / grid.tile_size_m)}"
            meta = TileMeta(tile=new_key, patch_size_m=store.meta.patch_size_m, crs=store.meta.crs,
                            textures=store.meta.textures)
            tile_dir = dst / "tiles" / new_key
            write_tile_tables(tile_dir, None, f_sorted, patches, meta)
            if labels is not None:  # same cells one span north: j shifts by span / patch y size
                dj = round(span_m / grid.size_m[1])
                ijk = grid.unpack(store.patches()["patch"])
                ijk[:, 1] += dj
                old = dict(zip(grid.pack(ijk).tolist(), labels["label"].tolist()))
                lab = np.array([old.get(p, 0) for p in patches["patch"].tolist()], np.int8)
                write_side_table(tile_dir, "labels", {"patch": patches["patch"], "label": lab}, meta)
    return dst


def _line(name: str, r: dict) -> str:
    return (f"{name}: {r['faces']:,} triangles in {r['tiles']} tiles, {r['wall_s']:.1f} s wall / {r['cpu_s']:.1f} s CPU"
            f" = {r['faces'] / r['wall_s']:,.0f} triangles/s; peak RSS {r['peak_rss_mb']:,.0f} MB")


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--work-dir", type=Path, default=REPO / "ms3d-work" / "demo", help="a processed work dir (read only)")
    p.add_argument("--bench", type=Path, default=REPO / "ms3d-work" / "output-bench")
    p.add_argument("--replicate", type=int, default=2, help="the larger campus is this many times the input")
    p.add_argument("--no-export", action="store_true", help="measure merge only")
    p.add_argument("--processes", type=int, default=2, help="also measure merge + export on this many processes")
    p.add_argument("--child", nargs=3, metavar=("STEP", "WORK", "PROCESSES"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        fn = {"merge": _child_merge, "export": _child_export}[a.child[0]]
        print(json.dumps(fn(a.child[1], int(a.child[2]))))
        return {}
    if not (a.work_dir / "campus.json").exists():
        print(f"{a.work_dir} is not a processed work dir: run `make demo` (or ms3d run) first")
        return {}
    load = os.getloadavg()
    print(f"input {a.work_dir}; load average {load[0]:.1f} on {os.cpu_count()} cores")
    results: dict[str, dict] = {}
    base = link_stores(a.work_dir, a.bench / "base")
    t = time.perf_counter()
    big = replicate_stores(a.work_dir, a.bench / "big", a.replicate)
    print(f"larger campus: x{a.replicate} ({time.perf_counter() - t:.0f} s to build its stores)")
    for size, work in (("base", base), ("big", big)):
        results[f"merge-{size}"] = m = _run_child("merge", work)
        if m["failed"]:
            print(f"  failed tiles: {m['failed'][:3]}")
        print(_line(f"merge  {size:4s}", m) + f"; slowest tile {m['slowest_tile_s']:.1f} s "
              f"({m['largest_tile_faces']:,} faces)")
        if not a.no_export:
            results[f"export-{size}"] = e = _run_child("export", work)
            print(_line(f"export {size:4s}", e))
    m, mb = results["merge-base"], results["merge-big"]
    figures = {"merge_triangles_per_s": m["faces"] / m["wall_s"], "merge_triangles_per_cpu_s": m["faces"] / m["cpu_s"],
               "merge_peak_rss_mb": [m["peak_rss_mb"], mb["peak_rss_mb"]], "faces": [m["faces"], mb["faces"]],
               "tiles": [m["tiles"], mb["tiles"]], "load_average": [load[0], os.getloadavg()[0]]}  # fmt: skip
    if not a.no_export:
        e, eb = results["export-base"], results["export-big"]
        both = m["faces"] / (m["wall_s"] + e["wall_s"])
        figures |= {"export_triangles_per_s": e["faces"] / e["wall_s"],
                    "merge_export_triangles_per_s": both,
                    "merge_export_triangles_per_cpu_s": m["faces"] / (m["cpu_s"] + e["cpu_s"]),
                    "export_peak_rss_mb": [e["peak_rss_mb"], eb["peak_rss_mb"]]}  # fmt: skip
        print(f"merge + export, 1 process: {both:,.0f} triangles/s wall, "
              f"{figures['merge_export_triangles_per_cpu_s']:,.0f} per CPU second (target >= {TARGET_TRIANGLES_PER_S:,})")
    if a.processes > 1:
        for work in (base,):  # reruns from scratch: the merged tiles and the output go first
            for p_ in list((work / "tiles").glob("*/merged.*")) + [work / "manifest.d"]:
                shutil.rmtree(p_) if p_.is_dir() else p_.unlink()
            shutil.rmtree(work / "output", ignore_errors=True)
            shutil.rmtree(work / "export", ignore_errors=True)
        results["merge-parallel"] = mp = _run_child("merge", base, a.processes)
        print(_line(f"merge  {a.processes} processes", mp) + " (peak: the largest pool worker's)")
        figures["merge_triangles_per_s_parallel"] = mp["faces"] / mp["wall_s"]
        if not a.no_export:
            results["export-parallel"] = ep = _run_child("export", base, a.processes)
            print(_line(f"export {a.processes} processes", ep) + " (peak: the parent's; pool workers not measured)")
            figures["merge_export_triangles_per_s_parallel"] = mp["faces"] / (mp["wall_s"] + ep["wall_s"])
            print(f"merge + export, {a.processes} processes: {figures['merge_export_triangles_per_s_parallel']:,.0f} "
                  f"triangles/s wall")
    print(f"peak RSS of merge: {m['peak_rss_mb']:,.0f} MB at {m['tiles']} tiles, {mb['peak_rss_mb']:,.0f} MB at "
          f"{mb['tiles']} tiles (x{mb['peak_rss_mb'] / m['peak_rss_mb']:.2f} for x{mb['faces'] / m['faces']:.1f} the "
          f"faces; budget {RSS_BUDGET_MB} MB)")
    print(json.dumps(figures))
    return {"figures": figures, "runs": results}


if __name__ == "__main__":
    main()
