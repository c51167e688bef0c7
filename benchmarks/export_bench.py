"""Export throughput, output size per km² and peak RSS, on the demo campus.

Stands in for the merge stage with ``synth.tile_meshes``: the demo mesh cut into ground tiles
(``--tile-size``, default 50 m) with faked provenance. Then, each in a fresh process (so its peak RSS is
its own):

1. ``run_export`` uncompressed on the demo campus: triangles per second (leaf triangles / wall seconds,
   and per CPU second), bytes per km² of campus footprint, peak RSS;
2. the same with Draco: bytes per km²; then uncompressed with 2 processes (``workers=2``);
3. ``run_export`` on a campus ``--replicate`` times larger (the demo's tiles copied side by side, same
   content per tile): peak RSS, which must not grow with the campus (memory is bounded by a tile).

Every run prints per node (leaf, parent, overview) its seconds and peak RSS (VmHWM reset before each node,
as a flow's worker records it) and the RSS the node started from. ``--merged WORKDIR`` exports the merged
tiles of a processed work dir (``tiles/*/merged.*`` and the textures they name; copied, never written)
instead of the fake merge; ``--code DIR`` runs the export of another checkout (e.g. ``git archive HEAD``
unpacked) for a side-by-side before/after; ``--quick`` skips the Draco and 2-process runs.

``export_bench.py formats ...`` runs :mod:`benchmarks.tile_formats_bench` instead (the same arguments): bytes on
disk and gzipped per level, texture and GPU texture bytes, export and viewer time, for geometry none / Draco /
meshopt, textures JPEG / KTX2, textured vs vertex-coloured parents, with the viewer's images of each.

Target: >= 40 k triangles/s for merge + export on this 2-core machine; this script measures
export (merge comes later); peak RSS < 2 GB. Always exits 0: it reports.

    .venv/bin/python benchmarks/export_bench.py                     # ms3d-work/demo-input (made if missing)
    .venv/bin/python benchmarks/export_bench.py --input ms3d-work/tiny-input --tile-size 25 --work /tmp/eb
    .venv/bin/python benchmarks/export_bench.py --merged /tmp/demo-work --quick --work /tmp/eb [--code /tmp/old]
    .venv/bin/python benchmarks/export_bench.py formats --merged /tmp/demo-work --shots docs/  # formats, LOD textures
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:
    sys.path.insert(0, str(REPO))

TARGET_TRIANGLES_PER_S = 40_000
RSS_BUDGET_MB = 2048


def _vm_hwm_mb() -> float:
    """Peak RSS of this process image (VmHWM; ru_maxrss would carry the parent's peak across exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _vm_rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _timed_nodes(jobs: list, per_node: list[dict]) -> list[dict]:
    """map_jobs for run_export: build each node here, noting its seconds and peak RSS (VmHWM reset first)."""
    from tasks.export import build_node
    from tasks.units import peak_rss_mb, reset_peak_rss

    out = []
    for job in jobs:
        start_mb = _vm_rss_mb()
        reset_peak_rss()
        t, c = time.perf_counter(), time.process_time()
        out.append(build_node(job))
        per_node.append({"node": job.node.key, "s": round(time.perf_counter() - t, 2),
                         "cpu_s": round(time.process_time() - c, 2), "peak_rss_mb": round(peak_rss_mb()),
                         "start_rss_mb": round(start_mb), "faces": out[-1].get("faces")})
    return out


def _leave_residue(mb: int) -> None:
    """Emulate what earlier stages leave in a Dask worker: ``mb`` MB allocated and freed (1 in 16 blocks
    kept, so the heap cannot shrink from its top) by another thread, i.e. in another glibc malloc arena,
    as a worker's thread pool does. Freed, but still resident until someone trims it."""
    import threading

    import numpy as np

    kept: list = []

    def churn() -> None:
        big = np.ones(30 << 20, np.uint8)  # freeing a 30 MB mapping raises glibc's mmap threshold to it
        del big
        blocks = [np.ones(1 << 20, np.uint8) for _ in range(mb)]  # 1 MB blocks: now from this thread's heap
        kept.extend(blocks[15::16])
        blocks.clear()

    t = threading.Thread(target=churn)
    t.start()
    t.join()
    _RESIDUE.extend(kept)


_RESIDUE: list = []


def _child(work: str, compression: str, workers: int = 1, residue_mb: int = 0) -> None:
    """Run one export in this (fresh) process and print its summary with peak RSS and CPU seconds."""
    from functools import partial

    from tasks.config import ExportConfig
    from tasks.export import run_export

    if residue_mb:
        _leave_residue(residue_mb)
    per_node: list[dict] = []
    t0, c0 = time.perf_counter(), time.process_time()
    mapper = partial(_timed_nodes, per_node=per_node) if workers == 1 else None
    summary = run_export(work, ExportConfig(compression=compression), workers=workers, map_jobs=mapper)
    summary.update(wall_s=time.perf_counter() - t0, cpu_s=time.process_time() - c0, peak_rss_mb=_vm_hwm_mb(),
                   children_peak_rss_mb=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0,
                   per_node=per_node)
    summary.pop("built"), summary.pop("reused")
    print(json.dumps(summary))


def _run_child(work: Path, compression: str, workers: int = 1, code: Path = REPO, residue_mb: int = 0) -> dict:
    env = {**os.environ, "PYTHONPATH": str(code), "OMP_NUM_THREADS": "1"}
    run = subprocess.run([sys.executable, __file__, "--child", str(work), compression, str(workers), "--code", str(code),
                          "--residue-mb", str(residue_mb)], capture_output=True, text=True, cwd=code, check=False,
                         env=env)  # fmt: skip
    if run.returncode != 0:
        raise RuntimeError(run.stderr[-3000:])
    return json.loads(run.stdout.strip().splitlines()[-1])


def make_merged(input_dir: Path, work: Path, tile_size_m: float, seed: int = 0) -> tuple[Path, float]:
    """Fake merge output of a synth campus; returns (work dir, footprint km² = tiles x tile area)."""
    import yaml

    from storage.frame import CampusFrame
    from synth.tile_meshes import fake_merged_workdir, read_production

    cfg = yaml.safe_load((input_dir / "campus.yaml").read_text())
    mesh, origin = read_production(input_dir / "mesh")  # placed by mesh/metadata.xml
    frame = CampusFrame(origin=origin, crs=cfg["inputs"]["crs"], vertical_datum="ellipsoidal (WGS 84), synthetic")
    fake_merged_workdir(mesh, frame, work, tile_size_m=tile_size_m, seed=seed)
    return work, _footprint_km2(work, tile_size_m)


def copy_merged(src: Path, work: Path, tile_size_m: float) -> tuple[Path, float]:
    """Copy a processed work dir's campus.json and merged tiles (texture paths made absolute, so the
    copies read the source's textures); returns (work dir, footprint km²)."""
    from storage.contracts.tile_mesh import read_tile_mesh, write_tile_mesh

    (work / "tiles").mkdir(parents=True)
    shutil.copy(src / "campus.json", work / "campus.json")
    for meta in sorted((src / "tiles").glob("*/merged.json")):
        write_tile_mesh(work / "tiles" / meta.parent.name, read_tile_mesh(meta.parent))
    return work, _footprint_km2(work, tile_size_m)


def _print_nodes(name: str, r: dict) -> None:
    for n in r.get("per_node", []):
        print(f"  {name} {n['node']:10s} {n['s']:7.2f} s ({n['cpu_s']:.2f} s CPU), peak RSS {n['peak_rss_mb']:6,} MB "
              f"(from {n['start_rss_mb']:,} MB), faces {n['faces']}")


def _footprint_km2(work: Path, tile_size_m: float) -> float:
    return len(list((work / "tiles").glob("*/merged.json"))) * tile_size_m**2 / 1e6


def replicate(src: Path, dst: Path, times: int, tile_size_m: float) -> Path:
    """A campus ``times`` as wide: src's tiles copied side by side along x (shifted keys and vertices)."""
    import numpy as np

    from storage.contracts.tile_mesh import read_tile_mesh, write_tile_mesh

    if dst.exists():
        shutil.rmtree(dst)
    dst.mkdir(parents=True)
    shutil.copy(src / "campus.json", dst / "campus.json")
    keys = sorted(p.parent.name for p in (src / "tiles").glob("*/merged.json"))
    ix = [int(k.split("_")[0]) for k in keys]
    span = max(ix) - min(ix) + 1
    for k in keys:
        tm = read_tile_mesh(src / "tiles" / k)
        i, j = (int(v) for v in k.split("_"))
        for r in range(times):
            shift = np.array([r * span * tile_size_m, 0, 0], np.float32)
            key = f"{i + r * span}_{j}"
            write_tile_mesh(dst / "tiles" / key, replace(tm, tile=key, vertices=tm.vertices + shift))
    return dst


def _residue_run(base: Path, work: Path, code: Path, residue_mb: int) -> dict:
    """The export in a process that first leaves ``residue_mb`` MB freed in another arena; prints per node."""
    if work.exists():
        shutil.rmtree(work)
    shutil.copytree(base, work)
    r = _run_child(work, "none", 1, code, residue_mb)
    print(f"export after {residue_mb:,} MB of freed residue in another arena: {r['wall_s']:.1f} s wall; "
          f"max node peak RSS {max(n['peak_rss_mb'] for n in r['per_node']):,} MB")
    _print_nodes("residue", r)
    return r


def main(argv: list[str] | None = None) -> dict:
    args = sys.argv[1:] if argv is None else list(argv)
    if args[:1] == ["formats"]:  # the output formats side by side: benchmarks/tile_formats_bench.py
        from benchmarks.tile_formats_bench import main as formats_main

        formats_main(args[1:])
        return {}
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--input", type=Path, default=REPO / "ms3d-work" / "demo-input")
    p.add_argument("--work", type=Path, default=REPO / "ms3d-work" / "export-bench")
    p.add_argument("--tile-size", type=float, default=50.0)
    p.add_argument("--replicate", type=int, default=2, help="the larger campus is this many times the input")
    p.add_argument("--merged", type=Path, help="a processed work dir whose merged tiles to export (copied)")
    p.add_argument("--code", type=Path, default=REPO, help="the checkout whose export runs (default: this one)")
    p.add_argument("--quick", action="store_true", help="skip the Draco and 2-process runs")
    p.add_argument("--residue-mb", type=int, default=0,
                   help="also run the demo export after leaving this many MB freed in another malloc arena "
                        "(what earlier stages leave in a Dask worker)")
    p.add_argument("--child", nargs=3, metavar=("WORK", "COMPRESSION", "WORKERS"), help=argparse.SUPPRESS)
    a = p.parse_args(argv)
    if a.child:
        sys.path.insert(0, str(a.code.resolve()))
        _child(a.child[0], a.child[1], int(a.child[2]), a.residue_mb)
        return {}
    if a.merged is None and not (a.input / "campus.yaml").exists():  # the demo campus, generated once (~3 min)
        subprocess.run([sys.executable, "-m", "flows.cli", "synth", "--preset", "demo", "--seed", "7", "--out",
                        str(a.input), "--overwrite"], check=True, cwd=REPO)  # fmt: skip
    load = os.getloadavg()
    base = a.work / "merged"
    if base.exists():
        shutil.rmtree(base)
    t = time.perf_counter()
    if a.merged is not None:
        tile_m = float(json.loads((a.merged / "campus.json").read_text()).get("grid", {}).get("tile_size_m", 100.0))
        a.tile_size = tile_m
        base, km2 = copy_merged(a.merged, base, tile_m)
    else:
        base, km2 = make_merged(a.input, base, a.tile_size)
    print(f"input {(a.merged or a.input).name} (export code {a.code}): {len(list((base / 'tiles').glob('*/merged.json')))} tiles of {a.tile_size:g} m, "
          f"{km2:.4f} km² (fake merge {time.perf_counter() - t:.1f} s); load average {load[0]:.1f}")

    results = {}
    runs = (("none", "none", 1),) if a.quick else (("none", "none", 1), ("draco", "draco", 1), ("none-2w", "none", 2))
    for name, compression, workers in runs:
        work = a.work / f"run-{name}"
        if work.exists():
            shutil.rmtree(work)
        shutil.copytree(base, work)
        results[name] = r = _run_child(work, compression, workers, a.code)
        rss_note = (f"peak RSS {r['peak_rss_mb']:,.0f} MB" if workers == 1 else
                    f"peak RSS of the parent {r['peak_rss_mb']:,.0f} MB (pool workers not measured)")
        print(f"export {name:7s} ({workers} process{'es' if workers > 1 else ''}): {r['leaf_faces']:,} triangles in "
              f"{r['wall_s']:.1f} s wall / {r['cpu_s']:.1f} s CPU = {r['leaf_faces'] / r['wall_s']:,.0f} triangles/s "
              f"(target >= {TARGET_TRIANGLES_PER_S:,} for merge + export); {r['bytes'] / 1e6:,.1f} MB = "
              f"{r['bytes'] / 1e6 / km2:,.0f} MB/km² (textures {r['texture_bytes'] / 1e6 / km2:,.0f}); "
              f"{rss_note}")
        _print_nodes(name, r)
    if a.residue_mb:
        results["residue"] = _residue_run(base, a.work / "run-residue", a.code, a.residue_mb)
    big = replicate(base, a.work / "big", a.replicate, a.tile_size)
    results["big"] = rb = _run_child(big, "none", 1, a.code)
    _print_nodes("big", rb)
    load_end = os.getloadavg()[0]
    km2_big = _footprint_km2(big, a.tile_size)
    rss = [results["none"]["peak_rss_mb"], rb["peak_rss_mb"]]
    print(f"peak RSS of export: {rss[0]:,.0f} MB at {km2:.3f} km² ({results['none']['tiles']} tiles), "
          f"{rss[1]:,.0f} MB at {km2_big:.3f} km² ({rb['tiles']} tiles): x{rss[1] / rss[0]:.2f} for x{km2_big / km2:.1f} "
          f"the area (budget {RSS_BUDGET_MB} MB); {rb['leaf_faces'] / rb['wall_s']:,.0f} triangles/s")
    figures = {
        "triangles_per_s": results["none"]["leaf_faces"] / results["none"]["wall_s"],
        "triangles_per_cpu_s": results["none"]["leaf_faces"] / results["none"]["cpu_s"],
        "mb_per_km2": results["none"]["bytes"] / 1e6 / km2,
        "node_peak_rss_mb": [max(n["peak_rss_mb"] for n in results[k]["per_node"]) for k in ("none", "big")],
        "peak_rss_mb": rss, "area_km2": [km2, km2_big], "load_average": [load[0], load_end],
    }
    if not a.quick:
        figures["triangles_per_s_2_processes"] = results["none-2w"]["leaf_faces"] / results["none-2w"]["wall_s"]
        figures["mb_per_km2_draco"] = results["draco"]["bytes"] / 1e6 / km2
    print(json.dumps(figures))
    return {"figures": figures, "runs": results}


if __name__ == "__main__":
    main()
