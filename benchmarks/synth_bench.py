"""Synth benchmark: generation time and memory, MLS rays/s, campus scaling, realism against real data,
and the baseline quality of the MVS mesh.

    .venv/bin/python benchmarks/synth_bench.py [--seed 7] [--campus-scales 0.5 1.0] [--skip-campus]

Real-data figures printed beside ours (from real captures):
  street MLS, 32-channel spinner: wall density p50 ~2,500 pts/m^2 within 5 m of the track, ~700 at 5-10 m,
  ~370 at 10-20 m (the paper's RIEGL VMX-450: ~4,000 pts/m^2 at 10 m); flat-wall noise RMS ~5 mm within one
  rotation, ~11 mm over one pass; wall offsets between passes ~1-5 cm.
  refined UAV/MVS mesh: edge length p10/p50/p90 ~9/12/23 cm, ~100 faces/m^2 (~160 on facades),
  roughness RMS ~8 mm on 0.5 m facade patches, 91 % of vertices of valence 6.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ROOT, machine

_CHILD = """
import json, sys, time
from synth.generate import generate
t = time.perf_counter()
out = generate(sys.argv[1], seed=int(sys.argv[2]), out=sys.argv[3], scale=float(sys.argv[4]))
hwm = [l for l in open('/proc/self/status') if l.startswith('VmHWM')][0].split()[1]
print(json.dumps({"seconds": time.perf_counter() - t, "peak_rss_mb": int(hwm) / 1024}))
"""


def generate_in_child(preset: str, seed: int, out: Path, scale: float = 1.0) -> dict:
    """Run generate() in a fresh process; its wall time and peak RSS (VmHWM), plus output counts."""
    r = subprocess.run([sys.executable, "-c", _CHILD, preset, str(seed), str(out), str(scale)],
                       capture_output=True, text=True, cwd=ROOT)
    if r.returncode:
        raise RuntimeError(r.stderr[-3000:])
    res = json.loads(r.stdout.strip().splitlines()[-1])
    scene = json.loads((out / "truth" / "scene.json").read_text())
    res.update(scene["stats"])
    res["buildings"] = len(scene["buildings"])
    res["area_km2"] = scene["extent_m"][0] * scene["extent_m"][1] / 1e6
    res["bytes"] = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    return res


def realism(seed: int) -> dict:
    """Rebuild the demo campus in memory (same seed, same streams as generate) and measure it."""
    from synth.generate import _tile_scene, streams
    from synth.mesh_realism import mesh_stats
    from synth.mls import MlsChunk, MlsParams, simulate_mls, with_density
    from synth.mvs import MvsParams, make_mvs_mesh
    from synth.presets import get_preset
    from synth.realism import mls_wall_stats
    from synth.trajectory import TrajectoryParams, build_trajectories

    p = get_preset("demo")
    scene = _tile_scene(seed, p, 0, 0, 1)
    r_mvs, _, r_traj, r_mls, _ = streams(seed * 7919 + 1, 5)
    mvs, defects = make_mvs_mesh(r_mvs, scene, MvsParams(edge_facade_m=p.mvs_edge_m))
    ms = mesh_stats(mvs.vertices, mvs.faces)
    trajs = build_trajectories(scene.roads, TrajectoryParams(n_passes=p.n_passes), r_traj, truth=scene.truth)
    out = {"mesh": ms, "mls": {}}
    for label, scale in (("demo preset", p.mls_density_scale), ("real-like density 0.15", 0.15)):
        params = with_density(MlsParams.vmx450(), scale)
        t0 = time.perf_counter()
        chunks = list(simulate_mls(scene, trajs[:2], params, np.random.default_rng(seed)))
        secs = time.perf_counter() - t0
        rays = sum(c.n_rays for c in chunks)
        cloud = MlsChunk.concat([c for c in chunks if len(c)])
        out["mls"][label] = (mls_wall_stats(cloud, trajs[:2], scene.truth), rays / secs, len(cloud))
    from synth.defects import facade_patch_bad_fraction

    out["bad_fraction"] = facade_patch_bad_fraction(mvs, defects)
    out["n_defects"] = len(defects)
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--campus-scales", type=float, nargs=2, default=(0.5, 1.0))
    ap.add_argument("--skip-campus", action="store_true")
    ap.add_argument("--campus-only", action="store_true")
    ap.add_argument("--keep", type=Path, default=None, help="keep the generated demo campus here")
    a = ap.parse_args(argv)
    print(f"machine: {machine()}\n")
    if not a.campus_only:
        demo_and_realism(a)
    if a.skip_campus:
        return
    campus_scaling(a)


def demo_and_realism(a) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        demo_dir = a.keep or Path(tmp) / "demo"
        d = generate_in_child("demo", a.seed, demo_dir)
        print("== demo preset generation (fresh process) ==")
        print(f"time {d['seconds']:.1f} s, peak RSS {d['peak_rss_mb']:.0f} MB, {d['buildings']} buildings, "
              f"{d['area_km2']:.3f} km^2, {d.get('points', 0):,} MLS points, {d.get('mvs_faces', 0):,} MVS faces, "
              f"{d['rays']:,} rays, {d['bytes'] / 1e6:.0f} MB written\n")

        print("== realism of the demo campus against real captures ==")
        r = realism(a.seed)
        real_d = (2500, 700, 370)
        for label, (ws, rays_s, n) in r["mls"].items():
            print(f"MLS ({label}; {n:,} points from 2 passes; {rays_s / 1e6:.2f} M rays/s simulated):")
            for (lo, hi), ours, real in zip(ws.bands_m, ws.density_p50, real_d):
                print(f"  wall density p50 {lo:>4g}-{hi:<4g} m: {ours:8,.0f} pts/m^2   real ~{real:,}")
            print(f"  flat-wall noise RMS within one rotation: {1e3 * ws.noise_rms_rotation_m:5.1f} mm   real ~5")
            print(f"  flat-wall noise RMS over one pass:       {1e3 * ws.noise_rms_pass_m:5.1f} mm   real ~11")
            print(f"  wall offset between passes (median):     {1e3 * ws.pass_offset_median_m:5.1f} mm   real 10-50")
        ms = r["mesh"]
        print("MVS mesh:")
        print(f"  edge length p10/p50/p90: {100 * ms.edge_p10_m:.1f}/{100 * ms.edge_p50_m:.1f}/{100 * ms.edge_p90_m:.1f} cm"
              "   real ~9/12/23")
        print(f"  faces per m^2: {ms.faces_per_m2:.0f} overall, {ms.facade_faces_per_m2:.0f} on facades   real ~100 / ~160")
        print(f"  facade roughness RMS (0.5 m patches): {1e3 * ms.facade_roughness_rms_m:.1f} mm   real ~8")
        print(f"  vertices of valence 6: {100 * ms.valence6_fraction:.0f} %   real 91 %")
        print(f"  injected defects: {r['n_defects']}; facade patches touched by a defect: "
              f"{100 * r['bad_fraction']:.0f} %   (paper: 425 of 1000 pairs bad)\n")

        print("== baseline quality of the demo MVS mesh against the truth (what later stages must beat) ==")
        from tasks.quality.truth import quality_of_campus

        t0 = time.perf_counter()
        q = quality_of_campus(demo_dir)
        print(q)
        print(f"(evaluated in {time.perf_counter() - t0:.0f} s)\n")


def campus_scaling(a) -> None:
    print("== campus preset at two sizes (tile by tile; peak RSS must not grow with the campus) ==")
    rows = []
    for s in a.campus_scales:
        with tempfile.TemporaryDirectory() as tmp:
            c = generate_in_child("campus", a.seed, Path(tmp) / "campus", scale=s)
            rows.append((s, c))
            print(f"scale {s:g}: {c['area_km2']:.3f} km^2, {c['buildings']} buildings, {c.get('points', 0):,} points, "
                  f"{c.get('mvs_faces', 0):,} MVS faces, {c['seconds']:.0f} s, "
                  f"{c['rays'] / c['seconds'] / 1e6:.2f} M rays/s overall, peak RSS {c['peak_rss_mb']:.0f} MB", flush=True)
    (s0, c0), (s1, c1) = rows
    print(f"area x{c1['area_km2'] / c0['area_km2']:.1f}, points x{c1.get('points', 1) / max(c0.get('points', 1), 1):.1f}, "
          f"peak RSS x{c1['peak_rss_mb'] / c0['peak_rss_mb']:.2f}")


if __name__ == "__main__":
    main()
