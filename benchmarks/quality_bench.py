"""Quality of the repaired campus against the synth truth: is the repair worth it?

    nice -n 10 .venv/bin/python benchmarks/quality_bench.py --synth SYNTH_DIR --work WORK_DIR \
        [--out OUT_DIR] [--variants a,b,c,d,e] [--grade-noise 0.12] [--max-regions N]

SYNTH_DIR is a ``ms3d synth`` campus (its truth/), WORK_DIR the work dir of ``ms3d run`` on it (patch
stores + labels). Variants, each measured on the whole campus:

  (a) the input MVS mesh;
  (b) screened Poisson of the MLS alone (thinned to 5 cm, normals oriented towards the vehicle path
      given by the camera centres, per 100 m tile with 5 m overlap, density-trimmed);
  (c) fusion everywhere, without classification (every patch graded bad);
  (d) ms3d with the true labels (the upper bound);
  (e) ms3d with the model's grades: the classify stage's grades.parquet when the work dir has them,
      else the labels with a fraction ``--grade-noise`` of the patches flipped (said in the output).

Figures: F-score at 5 and 10 cm, mean accuracy and completeness, uncovered facade area (no surface
within +-20 cm along the true normal), over all facades and over the facades the MLS saw (truth
facade area within 10 cm of a registered MLS point), per class; per region: time and peak RSS.
The repair variants run in sandboxes under OUT_DIR (tile folders of symlinks + their own grades), so
WORK_DIR is only read. The held-out seed of this benchmark is recorded in QUALITY_SEED.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _quality_eval import evaluate, mls_seen, region_figures, region_lines, subdivided_truth, table


class RssSampler:
    """Peak resident set size of this process while a block runs (a thread reads /proc every 10 ms)."""

    def __init__(self, period_s: float = 0.01):
        self.period, self.peak, self._stop = period_s, 0, threading.Event()

    @staticmethod
    def rss() -> int:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self.rss())
            time.sleep(self.period)

    def __enter__(self):
        self.peak = self.rss()
        self._t = threading.Thread(target=self._run, daemon=True)
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self.rss())


# ----------------------------------------------------------------------------------------- sandboxes

def make_sandbox(work: Path, out: Path, grades: dict[str, np.ndarray] | None) -> Path:
    """A work dir whose tiles are symlinks to ``work``'s store files, with ``grades`` (tile -> (u,)
    int8 aligned with patches.parquet) written as its grades.parquet; regions/ and manifest are its own."""
    from storage.patches.read import PatchStore
    from storage.patches.write import write_side_table

    if out.exists():
        shutil.rmtree(out)
    (out / "tiles").mkdir(parents=True)
    shutil.copy(work / "campus.json", out / "campus.json")
    for td in sorted((work / "tiles").iterdir()):
        if not (td / "patches.parquet").exists():
            continue
        dst = out / "tiles" / td.name
        dst.mkdir()
        for f in td.iterdir():
            if f.name != "grades.parquet":
                (dst / f.name).symlink_to(f.resolve())
        if grades is not None and td.name in grades:
            store = PatchStore(dst)
            g = grades[td.name]
            write_side_table(dst, "grades", {"patch": store.patches()["patch"], "score": g.astype(np.float32),
                                             "grade": g.astype(np.int8)}, store.meta, model_hash="quality_bench")
    return out


def grades_for(work: Path, mode: str, noise: float, seed: int = 0) -> tuple[dict[str, np.ndarray], str]:
    """Per-tile grades for a variant: "all" (every patch bad), "labels", or "model" (grades.parquet
    when present, else labels with ``noise`` of the patches flipped). Returns (grades, description)."""
    from storage.patches.read import PatchStore

    rng = np.random.default_rng(seed)
    out, what = {}, mode
    for td in sorted((work / "tiles").iterdir()):
        if not (td / "patches.parquet").exists():
            continue
        s = PatchStore(td)
        n = len(s.patches()["patch"])
        lab = s.side("labels")
        lab = np.zeros(n, np.int8) if lab is None else lab["label"].astype(np.int8)
        if mode == "all":
            out[td.name] = np.ones(n, np.int8)
        elif mode == "labels":
            out[td.name] = lab
        else:
            g = s.side("grades")
            if g is not None:
                out[td.name] = g["grade"].astype(np.int8)
                what = "model grades (grades.parquet)"
            else:
                flip = rng.random(n) < noise
                out[td.name] = np.where(flip, 1 - lab, lab).astype(np.int8)
                what = f"labels with {100 * noise:.0f} % of patches flipped (no grades.parquet yet)"
    return out, what


def run_repair(sandbox: Path, max_regions: int | None = None, log=print) -> list[dict]:
    """run_regions then run_region for every region, one after the other, with time and peak RSS."""
    from storage.workdir.layout import WorkDir, read_campus
    from tasks.config import CampusConfig
    from tasks.regions import run_regions
    from tasks.repair import run_region

    wd = WorkDir(sandbox)
    cfg = CampusConfig.model_validate(read_campus(wd)["config"])
    cfg.repair.grades = "model"
    plan = run_regions(cfg, wd)
    keys = plan["regions"][:max_regions] if max_regions else plan["regions"]
    log(f"  {plan['n_regions']} regions ({plan['split']} split), {plan['n_patches_rebuilt']} patches")
    rows = []
    for i, k in enumerate(keys):
        c0 = time.process_time()
        with RssSampler() as rss:
            try:
                r = run_region(k, cfg, wd)
            except Exception as e:  # noqa: BLE001 - a bug in one region must not end the benchmark; it is reported
                import traceback

                r = {"unit": k, "status": "failed", "error": f"{type(e).__name__}: {e}",
                     "traceback": traceback.format_exc()[-2000:]}
        r["cpu_seconds"] = time.process_time() - c0
        r["peak_rss_mb"] = rss.peak / 2**20
        rows.append(r)
        if r.get("status") == "failed":
            log(f"  region {k} failed: {r.get('error')}")
        if (i + 1) % 25 == 0:
            log(f"  {i + 1}/{len(keys)} regions")
    return rows


# ----------------------------------------------------------------------------------------- assembly

def assemble(work: Path, with_regions: bool = True) -> tuple[np.ndarray, np.ndarray, dict]:
    """The campus mesh: every live tile's faces, minus the rows rebuilt regions replace, plus the
    rebuilt faces; welded by vertex id (new region vertices stay per region). Campus-local float64."""
    from storage.contracts.region_mesh import region_meshes_for_tile
    from storage.ids import TileId
    from storage.patches.read import PatchStore
    from storage.workdir.layout import WorkDir

    wd = WorkDir(work)
    tris, vids, n_rep, n_new = [], [], 0, 0
    cols = [f"{a}{v}" for v in range(3) for a in "xyz"] + ["vid0", "vid1", "vid2"]
    # negative ids are local to a region (shared by its pieces in different tiles): number them densely,
    # region after region, below every original id
    local: dict[str, np.ndarray] = {}
    if with_regions:
        for t in wd.live_tiles():
            for rm in region_meshes_for_tile(wd.root, TileId(t.ix, t.iy)):
                local[rm.region_id] = np.union1d(local.get(rm.region_id, np.zeros(0, np.int64)),
                                                 rm.vertex_ids[rm.vertex_ids < 0])
    base, offset, added = {}, 0, set()
    for k in sorted(local):
        base[k] = offset
        offset += len(local[k])
    for t in wd.live_tiles():
        _, f = PatchStore(wd.tile_dir(t)).read_all(point_columns=["x"], face_columns=cols)
        keep = np.ones(len(f["x0"]), bool)
        parts = region_meshes_for_tile(wd.root, TileId(t.ix, t.iy)) if with_regions else []
        for rm in parts:
            keep[rm.replaced_rows] = False
        tri = np.stack([np.stack([f[f"{a}{v}"] for a in "xyz"], 1) for v in range(3)], 1)[keep]
        vid = np.stack([f[f"vid{v}"] for v in range(3)], 1)[keep]
        tris.append(tri.astype(np.float64))
        vids.append(vid)
        n_rep += int((~keep).sum())
        for rm in parts:
            if rm.region_id in added:  # every tile a region reaches lists the whole region
                continue
            added.add(rm.region_id)
            rank = np.searchsorted(local[rm.region_id], rm.vertex_ids)
            vid_r = np.where(rm.vertex_ids >= 0, rm.vertex_ids, -1 - base[rm.region_id] - rank)
            tris.append(rm.vertices[rm.faces].astype(np.float64))
            vids.append(vid_r[rm.faces])
            n_new += len(rm.faces)
    tri = np.concatenate(tris)
    vid = np.concatenate(vids)
    _uid, first, inv = np.unique(vid.ravel(), return_index=True, return_inverse=True)
    return tri.reshape(-1, 3)[first], inv.reshape(-1, 3), {"replaced_faces": n_rep, "rebuilt_faces": n_new,
                                                           "faces": len(vid)}


def poisson_from_mls(work: Path, cams_centres: np.ndarray, spacing_m: float = 0.05, depth: int = 11,
                     overlap_m: float = 5.0, trim: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """(b): screened Poisson of the MLS alone, per tile (cropped back to the tile), campus-local."""
    import open3d as o3d

    from storage.patches.read import PatchStore
    from storage.workdir.layout import WorkDir
    from tasks.repair.fuse import thin_points

    wd = WorkDir(work)
    pts = []
    for t in wd.live_tiles():
        p, _ = PatchStore(wd.tile_dir(t)).read_all(point_columns=["x", "y", "z"], face_columns=["patch"])
        xyz = np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64)
        pts.append(xyz[thin_points(xyz, spacing_m)])
    xyz = np.concatenate(pts)
    tile = 100.0
    lo = np.floor(xyz[:, :2].min(0) / tile) * tile
    vs, fs, nv = [], [], 0
    cam_tree = __import__("scipy.spatial", fromlist=["cKDTree"]).cKDTree(cams_centres)
    for ix in np.arange(lo[0], xyz[:, 0].max(), tile):
        for iy in np.arange(lo[1], xyz[:, 1].max(), tile):
            sel = (xyz[:, 0] >= ix - overlap_m) & (xyz[:, 0] < ix + tile + overlap_m) & \
                  (xyz[:, 1] >= iy - overlap_m) & (xyz[:, 1] < iy + tile + overlap_m)
            if sel.sum() < 100:
                continue
            q = xyz[sel]
            c = q.mean(0)
            pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(q - c))
            pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(12))
            n = np.asarray(pcd.normals)
            _, j = cam_tree.query(q)
            flip = np.einsum("ij,ij->i", n, cams_centres[j] - q) < 0
            n[flip] *= -1
            pcd.normals = o3d.utility.Vector3dVector(n)
            with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
                mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth, n_threads=1)
            dens = np.asarray(dens)
            mesh.remove_vertices_by_mask(dens < np.quantile(dens, trim))
            v = np.asarray(mesh.vertices) + c
            f = np.asarray(mesh.triangles)
            cen = v[f].mean(1)
            own = (cen[:, 0] >= ix) & (cen[:, 0] < ix + tile) & (cen[:, 1] >= iy) & (cen[:, 1] < iy + tile)
            vs.append(v)
            fs.append(f[own] + nv)
            nv += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def generate_campus(out: Path, seed: int, mls_density: float | None = None, scale: float = 1.0) -> Path:
    """A demo-preset synth campus with the MLS density scale overridden (the preset API; the CLI's
    ``--mls-density`` does the same), then ``ms3d run`` on it inline. Returns the work dir."""
    from dataclasses import replace

    from flows.cli import main as cli
    from synth import presets
    from synth.generate import generate

    name = "demo"
    if mls_density is not None:
        name = f"demo-d{mls_density:g}"
        presets.PRESETS[name] = replace(presets.PRESETS["demo"], name=name, mls_density_scale=mls_density)
    generate(name, seed=seed, out=out / "synth", scale=scale, overwrite=True)
    work = out / "work"
    cli(["run", str(out / "synth" / "campus.yaml"), "--work-dir", str(work), "--set", "runner=inline"])
    return work


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--synth", type=Path, required=True)
    ap.add_argument("--work", type=Path, required=True)
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--variants", default="a,b,c,d,e")
    ap.add_argument("--grade-noise", type=float, default=0.12)
    ap.add_argument("--max-regions", type=int, default=None)
    ap.add_argument("--set", action="append", default=[], help="repair.* override for c/d/e, e.g. mesh.method=poisson")
    ap.add_argument("--report", type=Path, default=None, help="reprint the tables of an earlier run's OUT_DIR")
    a = ap.parse_args(argv)
    if a.report is not None:
        return print_report(a.report)
    from storage.workdir.layout import WorkDir, campus_frame, read_campus

    out = a.out or (a.work.parent / f"{a.work.name}-quality")
    out.mkdir(parents=True, exist_ok=True)
    doc = read_campus(WorkDir(a.work))
    origin = np.asarray(campus_frame(doc).origin, np.float64)
    t0 = time.perf_counter()
    truth = subdivided_truth(a.synth, origin)
    seen = mls_seen(*truth, a.work)
    print(f"truth: {len(truth[1])} faces ({seen.sum()} MLS-seen facade faces), {time.perf_counter() - t0:.0f} s", flush=True)
    results, regions, notes = {}, {}, {}
    for var in a.variants.split(","):
        t0, c0 = time.perf_counter(), time.process_time()
        if var == "a":
            v, f, _ = assemble(a.work, with_regions=False)
        elif var == "b":
            from tasks.config import CampusConfig
            from tasks.repair.stage import load_cameras

            cfg = CampusConfig.model_validate(doc["config"])
            cams = load_cameras(cfg, doc, campus_frame(doc))
            v, f = poisson_from_mls(a.work, np.stack([c.centre for c in cams]))
        else:
            mode = {"c": "all", "d": "labels", "e": "model"}[var]
            grades, notes[var] = grades_for(a.work, mode, a.grade_noise)
            sb = make_sandbox(a.work, out / f"variant-{var}", grades)
            if a.set:
                _apply_overrides(sb, a.set)
            print(f"({var}) {notes[var]}", flush=True)
            rows = run_repair(sb, a.max_regions)
            regions[var] = region_figures(rows)
            (out / f"regions-{var}.json").write_text(json.dumps(rows, default=str))
            v, f, info = assemble(sb)
            regions[var].update(info)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        results[var] = evaluate(v, f, truth, seen)
        results[var]["build_seconds"], results[var]["build_cpu_seconds"] = wall, cpu
        print(f"({var}) built in {wall:.0f} s wall / {cpu:.0f} s CPU; F@5 {results[var]['all']['F5']:.3f}", flush=True)
    report = {"synth": str(a.synth), "work": str(a.work), "notes": notes, "results": results, "regions": regions}
    (out / "quality.json").write_text(json.dumps(report, indent=1, default=float))
    return print_report(out)


def print_report(out: Path) -> dict:
    """Print the tables, the per-region lines and the region summaries of a finished run."""
    report = json.loads((out / "quality.json").read_text())
    for var, note in report.get("notes", {}).items():
        print(f"({var}) grades: {note}")
    print(table(report["results"]))
    for var in report["results"]:
        r = report["results"][var]
        print(f"({var}) built in {r.get('build_seconds', 0):.0f} s wall / {r.get('build_cpu_seconds', 0):.0f} s CPU")
    for var, summary in report.get("regions", {}).items():
        rows = json.loads((out / f"regions-{var}.json").read_text()) if (out / f"regions-{var}.json").exists() else []
        print("\n".join(region_lines(var, rows)))
        print(f"({var}) regions: {json.dumps(summary)}")
    return report


def _apply_overrides(sandbox: Path, sets: list[str]) -> None:
    """Write repair.* overrides into the sandbox's campus.json config snapshot."""
    import yaml

    p = sandbox / "campus.json"
    doc = json.loads(p.read_text())
    rep = doc["config"].setdefault("repair", {})
    for s in sets:
        key, val = s.split("=", 1)
        d = rep
        parts = key.split(".")
        for k in parts[:-1]:
            d = d.setdefault(k, {})
        d[parts[-1]] = yaml.safe_load(val)
    p.write_text(json.dumps(doc))


if __name__ == "__main__":
    main()
