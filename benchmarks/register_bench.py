"""Registration accuracy on the demo campus against the recorded truth (§3.1: SAC-IA + Scale-ICP).

    .venv/bin/python benchmarks/register_bench.py [--input DIR]

Prints rotation / translation / scale errors (targets: < 0.05 deg, < 2 cm, < 0.05 %), fitness, RMSE, time.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import ensure_demo, machine, truth_in_campus_frame


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser()
    ap.add_argument("--input", type=Path, default=None)
    a = ap.parse_args(argv)
    src = a.input or ensure_demo()
    from flows.campus import InlineExecutor, scan_inputs
    from storage.workdir.layout import WorkDir
    from tasks.config import CampusConfig
    from tasks.register.align import apply_similarity, compare_transforms
    from tasks.register.stage import run_register

    with tempfile.TemporaryDirectory() as tmp:
        cfg = CampusConfig.from_yaml(src / "campus.yaml", {"work_dir": tmp, "registration.mode": "auto"})
        wd = WorkDir(tmp)
        t0 = time.perf_counter()
        records, frame, *_ = scan_inputs(cfg, wd, InlineExecutor())
        t_scan = time.perf_counter() - t0
        reg = run_register(records, frame, cfg, wd)
        secs = time.perf_counter() - t0
    origin = frame.origin_array
    est = np.asarray(reg["matrix"])
    truth = truth_in_campus_frame(src, origin)
    pts = [r for r in records if r.kind == "points" and r.bounded]
    lo = np.min([r.lo for r in pts], axis=0) - origin
    hi = np.max([r.hi for r in pts], axis=0) - origin
    centre = (lo + hi) / 2
    err = compare_transforms(est, truth, at=centre)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    worst = float(np.linalg.norm(apply_similarity(est, corners) - apply_similarity(truth, corners), axis=1).max())
    print(f"machine: {machine()}")
    print(f"input: {src}")
    print(f"method: {reg.get('method')}; fitness {reg.get('fitness', float('nan')):.3f}, "
          f"inlier RMSE {1000 * reg.get('inlier_rmse_m', float('nan')):.1f} mm, time {secs:.1f} s "
          f"(scan of every input incl. mesh surface samples {t_scan:.1f} s, registration {secs - t_scan:.1f} s)")
    digest = hashlib.sha256(est.astype(np.float64).tobytes()).hexdigest()[:16]
    print(f"coarse stage fitness {reg.get('coarse_fitness', float('nan')):.3f}; transform digest {digest} "
          f"(the same on every run: the coarse consensus is seeded, tasks/register/sac.py)")
    print(f"rotation error    {err['rotation_error_deg']:.4f} deg   (target < 0.05)")
    print(f"translation error {100 * err['translation_error_m']:.2f} cm at the MLS extent centre (target < 2); "
          f"worst over the extent's corners {100 * worst:.2f} cm")
    print(f"scale error       {abs(err['scale_error_pct']):.4f} %   (target < 0.05)")
    ok = err["rotation_error_deg"] < 0.05 and err["translation_error_m"] < 0.02 and abs(err["scale_error_pct"]) < 0.05
    print("targets met" if ok else "TARGETS MISSED")
    return err | {"worst_corner_m": worst, "seconds": secs, "digest": digest}


if __name__ == "__main__":
    main()
