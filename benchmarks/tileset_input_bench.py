"""A 3D Tiles tileset as the mesh input: ms3d's own output read back, graded like the same geometry as OBJ.

1. ``ms3d synth`` a campus (default: the tiny preset; ``--preset demo`` for the demo) and ``ms3d run`` it;
   its ``output/tileset.json`` is the tileset input below;
2. the merged model it was exported from, written as one OBJ in the campus CRS (world metres, from the work
   dir's merged tiles, not from the tileset): the same geometry by another path;
3. ``ms3d run`` twice with the campus's points: ``inputs.mesh: [merged.obj]`` and ``inputs.mesh:
   [tileset.json]``; the grades of every patch compared between the two (patch key -> grade).

Prints the faces each input read, the registration each run applied, the graded pairs and the share of
patches whose grade agrees, and the wall time of each run. Usage:
``python benchmarks/tileset_input_bench.py [--preset tiny|demo] [--seed 7] [--keep DIR]``
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
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import machine

MS3D = [sys.executable, "-m", "flows.cli"]


def sh(args: list[str]) -> float:
    t0 = time.perf_counter()
    p = subprocess.run(args, capture_output=True, text=True, check=False)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(map(str, args[:4]))} ... failed ({p.returncode}): "
                         f"{(p.stderr.strip().splitlines() or ['?'])[-1]}")
    return time.perf_counter() - t0


def merged_obj(work: Path, out: Path) -> int:
    """The work dir's merged tiles as one OBJ in world metres (the campus CRS). Returns the face count."""
    from storage.contracts.tile_mesh import read_tile_mesh
    from storage.formats.meshes import MeshData, write_obj
    from storage.workdir.layout import WorkDir, campus_frame, read_campus

    origin = np.asarray(campus_frame(read_campus(WorkDir(work))).origin, np.float64)
    parts = []
    for d in sorted((work / "tiles").glob("*/merged.json")):
        tm = read_tile_mesh(d.parent)
        parts.append(MeshData(np.asarray(tm.vertices, np.float64) + origin, np.asarray(tm.faces, np.int64)))
    mesh = MeshData.concat(parts)
    write_obj(out, mesh.vertices, mesh.faces)  # world coordinates in the file
    return mesh.n_faces


def grades(work: Path) -> dict[tuple[str, int], int]:
    """(tile, patch id) -> grade of every patch graded in a work dir."""
    import pyarrow.parquet as pq

    out = {}
    for p in sorted((work / "tiles").glob("*/grades.parquet")):
        t = pq.read_table(p).to_pydict()
        key = "patch_id" if "patch_id" in t else next(k for k in t if "patch" in k)
        for pid, g in zip(t[key], t["grade"]):
            out[(p.parent.name, int(pid))] = int(g)
    return out


def run_with_mesh(campus: Path, mesh: Path, work: Path, crs: str) -> float:
    doc = yaml.safe_load((campus / "campus.yaml").read_text())
    inputs = doc["inputs"]
    inputs["mesh"] = [str(mesh)]
    inputs["crs"] = crs
    for k in ("points", "labels", "images", "cameras"):
        if k in inputs and inputs[k] is not None:
            v = inputs[k]
            inputs[k] = [str((campus / x).resolve()) for x in v] if isinstance(v, list) else str((campus / v).resolve())
    inputs.pop("images", None)  # textures come from the mesh; photos are not needed for grading
    inputs.pop("cameras", None)
    inputs.pop("mesh_offset", None)
    cfg = work.parent / f"{work.name}.yaml"
    cfg.write_text(yaml.safe_dump(doc))
    return sh(MS3D + ["run", str(cfg), "--work-dir", str(work), "--set", "runner=inline", "--set", "report.enabled=false"])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny", choices=["tiny", "demo"])
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--keep", type=Path, help="keep the campus and work dirs here")
    a = ap.parse_args(argv)
    tmp = tempfile.TemporaryDirectory(prefix="ms3d-tileset-bench-")
    root = (a.keep or Path(tmp.name)).absolute()
    root.mkdir(parents=True, exist_ok=True)
    print(f"machine: {machine()}; preset {a.preset}, seed {a.seed}; in {root}")
    campus = root / "campus"
    if not (campus / "campus.yaml").exists():
        sh(MS3D + ["synth", "--preset", a.preset, "--seed", str(a.seed), "--out", str(campus), "--overwrite"])
    first = root / "work-first"
    t_first = sh(MS3D + ["run", str(campus / "campus.yaml"), "--work-dir", str(first), "--set", "runner=inline",
                         "--set", "report.enabled=false"])
    crs = yaml.safe_load((campus / "campus.yaml").read_text())["inputs"]["crs"]
    obj = root / "merged.obj"
    n_obj = merged_obj(first, obj)
    tileset = first / "output" / "tileset.json"
    t_obj = run_with_mesh(campus, obj, root / "work-obj", crs)
    t_ts = run_with_mesh(campus, tileset, root / "work-tileset", crs)
    g_obj, g_ts = grades(root / "work-obj"), grades(root / "work-tileset")
    reg = {k: json.loads((root / f"work-{k}" / "campus.json").read_text()).get("registration", {})
           for k in ("obj", "tileset")}
    common = sorted(set(g_obj) & set(g_ts))
    agree = sum(g_obj[k] == g_ts[k] for k in common)
    print(f"first run (the tileset's source): {t_first:.1f} s; merged model {n_obj:,} faces")
    print(f"{'input':<10} {'wall s':>7} {'patches':>8} {'graded':>7} {'bad':>6}  registration")
    for name, g, t in (("OBJ", g_obj, t_obj), ("tileset", g_ts, t_ts)):
        vals = np.array(list(g.values()) or [-1])
        r = reg["obj" if name == "OBJ" else "tileset"]
        print(f"{name:<10} {t:>7.1f} {len(g):>8,} {int((vals >= 0).sum()):>7,} {int((vals == 1).sum()):>6,}  "
              f"{json.dumps(r.get('applied', r.get('status', r)))[:80]}")
    only = len(set(g_obj) ^ set(g_ts))
    print(f"patches in both: {len(common):,} (in one only: {only:,}); same grade: {agree:,} "
          f"({agree / max(len(common), 1):.2%})")
    if not a.keep:
        tmp.cleanup()


if __name__ == "__main__":
    main()
