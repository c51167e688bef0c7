"""The repair stage's regions, timed side by side: this checkout against another (``--code``).

Takes a processed work dir (``--work``, left untouched) and its campus config. For each code root, in a
fresh process, it mirrors the work dir into a scratch folder (every entry symlinked except the manifest
and the region outputs; the region plan and the occupancy cache copied) and runs
``tasks.repair.stage.run_region`` on every region of the plan, one after the other, as a worker does.
Prints per code root: regions run, wall seconds, the sum of each step's seconds from the region records,
the largest region's seconds and the highest peak RSS, and the ratio of the walls; then whether the
rebuilt regions are identical (sha256 of each region's written files). Always exits 0: it reports.

    .venv/bin/python benchmarks/region_bench.py --campus /tmp/q9103/campus/campus.yaml --work /tmp/s5/w9103 \\
        --code /tmp/old --scratch /tmp/rb [--every 5]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

CHILD = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
from storage.contracts.region_plan import read_plan
from storage.workdir.layout import WorkDir
from tasks.config import CampusConfig
from tasks.repair.stage import run_region
cfg = CampusConfig.from_yaml(sys.argv[2], {"work_dir": sys.argv[3]})
wd = WorkDir(cfg.work_dir)
plan = {r.key: r for r in read_plan(wd.root)}
t0 = time.perf_counter()
out = [run_region(k, cfg, wd, plan) for k in sorted(plan)[::int(sys.argv[4])]]
print(json.dumps({"wall": time.perf_counter() - t0, "summaries": out}, default=str))
"""


def mirror(work: Path, scratch: Path) -> None:
    """Scratch work dir: ``work``'s entries symlinked, but an empty manifest and a fresh regions folder
    holding only the plan and the occupancy cache."""
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    for p in work.iterdir():
        if p.name not in ("manifest.d", "manifest.parquet", "regions", ".lock"):
            (scratch / p.name).symlink_to(p.resolve())
    (scratch / "regions").mkdir()
    shutil.copy2(work / "regions" / "regions.json", scratch / "regions" / "regions.json")
    if (work / "regions" / "_occupancy").exists():
        shutil.copytree(work / "regions" / "_occupancy", scratch / "regions" / "_occupancy")


def digest(regions: Path) -> dict[str, str]:
    """{region: sha256 of its files' bytes, region.json without its timings}."""
    out = {}
    for d in sorted(p for p in regions.iterdir() if p.is_dir() and p.name.startswith("r")):
        h = hashlib.sha256()
        for f in sorted(d.iterdir()):
            data = f.read_bytes()
            if f.name == "region.json":
                doc = json.loads(data)
                doc.pop("summary", None)
                doc.get("stats", {}).pop("seconds", None)
                data = json.dumps(doc, sort_keys=True).encode()
            h.update(f.name.encode() + data)
        out[d.name] = h.hexdigest()
    return out


def run(code: Path, campus: Path, work: Path, scratch: Path, every: int = 1) -> dict:
    mirror(work, scratch)
    r = subprocess.run([sys.executable, "-c", CHILD, str(code), str(campus), str(scratch), str(every)],
                       capture_output=True, text=True, check=False)
    if r.returncode != 0:
        return {"error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}"}
    res = json.loads(r.stdout.strip().splitlines()[-1])
    steps, peak, largest = Counter(), 0.0, 0.0
    for s in res["summaries"]:
        for k, v in (s.get("step_seconds") or {}).items():
            steps[k] += v
        peak = max(peak, s.get("peak_rss_mb") or 0.0)
        largest = max(largest, (s.get("step_seconds") or {}).get("total", 0.0))
    return {"wall": res["wall"], "n": len(res["summaries"]), "steps": dict(steps), "peak": peak,
            "largest": largest, "digest": digest(scratch / "regions")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--campus", type=Path, required=True)
    ap.add_argument("--work", type=Path, required=True, help="a processed work dir (read only)")
    ap.add_argument("--code", type=Path, help="another checkout to run side by side")
    ap.add_argument("--scratch", type=Path, default=Path("/tmp/ms3d-region-bench"))
    ap.add_argument("--every", type=int, default=1, help="every k-th region of the plan (sorted by key)")
    a = ap.parse_args(argv)
    roots = [("this", REPO)] + ([("other", a.code.resolve())] if a.code else [])
    results = {}
    for name, root in roots:
        t = time.perf_counter()
        results[name] = run(root, a.campus.resolve(), a.work.resolve(), a.scratch / name, a.every)
        res = results[name]
        if "error" in res:
            print(f"{name} ({root}): failed: {res['error']}")
            continue
        steps = ", ".join(f"{k} {v:.1f}" for k, v in sorted(res["steps"].items(), key=lambda kv: -kv[1]))
        print(f"{name} ({root}): {res['n']} regions, wall {res['wall']:.1f} s ({time.perf_counter() - t:.0f} s with "
              f"set-up); largest region {res['largest']:.1f} s; peak RSS {res['peak']:.0f} MB\n  step sums: {steps}")
    if a.code and all("digest" in r for r in results.values()):
        this, other = results["this"], results["other"]
        same = sum(this["digest"].get(k) == v for k, v in other["digest"].items())
        print(f"wall this / other: {this['wall'] / other['wall']:.2f}; regions identical: {same} of "
              f"{len(other['digest'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
