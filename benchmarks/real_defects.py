"""Defect cases of a real mesh: labelled defects injected into a copy of a zero-defect case's mesh.

The zero-defect case (:mod:`benchmarks.real_cases`) holds a real mesh as the truth and an MLS ray-cast from
it. A defect case keeps that truth and that scan and replaces the input mesh by a copy with defects
(:func:`synth.mesh_defects.inject_mesh_defects`: holes, bridged recesses, melted balconies, protrusions,
dents, offsets, noise, missing thin structures), so the labels are exact::

    mesh.ply                 the defective mesh, EPSG:2154 world coordinates (float64)
    mls/                     the zero case's scan of the truth, copied
    truth/truth_mesh.ply     the real mesh (the truth), its face classes and registration, copied
    truth/defects.json       {"frame_origin": world origin, "defects": [...]}: samples in the local frame
    campus.yaml              ``inputs.labels: truth/defects.json`` (labels stage, quality against the truth)
    case.json                the zero case's record, the injection seed and rate, the defects by type

    .venv/bin/python benchmarks/real_defects.py --zero ms3d-work/real-cases/sceaux-zero \\
        --out ms3d-work/real-cases/sceaux-defects-1 --seed 1
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from storage.formats.meshes import read_mesh
from storage.formats.ply import write_ply
from synth.mesh_defects import MeshDefectParams, inject_mesh_defects

ROOT = Path(__file__).resolve().parents[1]
DEFECT_CASE_VERSION = 1


def defect_key(zero_doc: dict, seed: int, rate_scale: float) -> dict:
    return {"version": DEFECT_CASE_VERSION, "zero": zero_doc["key"], "seed": seed, "rate_scale": rate_scale}


def build_defect_case(zero: Path, out: Path, seed: int, rate_scale: float = 0.6, force: bool = False) -> Path:
    """Build (or reuse, when its case.json has the same key) a defect case of the zero case ``zero`` in
    ``out``: the same truth and scan, the input mesh with defects injected at ``rate_scale`` times the
    default rates, seeded by ``seed``."""
    zero, out = Path(zero), Path(out)
    zdoc = json.loads((zero / "case.json").read_text())
    key = defect_key(zdoc, seed, rate_scale)
    meta = out / "case.json"
    if not force and meta.exists() and json.loads(meta.read_text()).get("key") == key:
        return out
    t0 = time.perf_counter()
    origin = np.asarray(zdoc["world_origin"], np.float64)
    m = read_mesh(zero / "truth" / "truth_mesh.ply")
    local = np.asarray(m.vertices, np.float64) - origin
    v, f, defects = inject_mesh_defects(np.random.default_rng(seed), local, np.asarray(m.faces, np.int64),
                                        MeshDefectParams(rate_scale=rate_scale))
    if out.exists():
        shutil.rmtree(out)
    (out / "truth").mkdir(parents=True)
    write_ply(out / "mesh.ply", v + origin, f)
    shutil.copytree(zero / "mls", out / "mls")
    for name in ("truth_mesh.ply", "truth_mesh_faces.npz", "registration.json"):
        shutil.copy2(zero / "truth" / name, out / "truth" / name)
    (out / "truth" / "defects.json").write_text(json.dumps({"frame_origin": origin.tolist(), "defects": defects}))
    name = out.name
    cfg = {"name": name, "work_dir": f"../../{name}-work",
           "inputs": {"mesh": ["mesh.ply"], "points": ["mls"], "crs": zdoc["crs"], "labels": "truth/defects.json"},
           "registration": {"mode": "off"}}
    (out / "campus.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    doc = {"key": key, "case": "defects", "mesh": zdoc["mesh"], "source": zdoc["source"], "crs": zdoc["crs"],
           "world_origin": zdoc["world_origin"], "scale_factor_m_per_unit": zdoc["scale_factor_m_per_unit"],
           "zero_case": str(zero), "scan": zdoc["scan"], "faces": int(len(f)), "truth_faces": int(len(m.faces)),
           "area_m2": zdoc["area_m2"], "defects": len(defects),
           "defects_by_type": dict(sorted(Counter(d["type"] for d in defects).items())),
           "seconds": round(time.perf_counter() - t0, 1)}
    meta.write_text(json.dumps(doc, indent=1))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--zero", type=Path, default=ROOT / "ms3d-work" / "real-cases" / "sceaux-zero")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--rate-scale", type=float, default=0.6, help="every defect rate times this")
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args(argv)
    out = build_defect_case(a.zero, a.out, a.seed, a.rate_scale, a.force)
    print(json.dumps(json.loads((out / "case.json").read_text()), indent=1))


if __name__ == "__main__":
    main()
