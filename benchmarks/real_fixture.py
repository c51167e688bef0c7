"""Derive the committed real-mesh test fixture: a crop of the ContextCapture 3MXB street corner.

The source (``ProjSEED/Unity-3mx``, MIT licence, :mod:`benchmarks.real_cases` source ``ccstreet``) is
fetched, never committed whole. This script cuts the lane of its zero-defect case: every face whose centroid
lies in x 31..37 m, y 16..30 m (local metres, ground at 0) and below 13.5 m (both facades facing the lane,
the ground and the parked cars between them, no roof), as it was produced: its node borders, cracks and
duplicated vertices untouched. It writes ``tests/data/ccstreet_crop/mesh.npz``:

    vertices_mm  (n, 3) int16   millimetres from ``origin_m`` (local frame; exact to 0.5 mm)
    faces        (m, 3) uint16  vertex indices, as in the source (no weld, no reorder)
    origin_m     (3,) float64   the crop's local origin (metres, the case's local frame)
    lane_m       (2, 2) float64 the lane the test's scan drives along (local metres)

with its README and the source's licence beside it.

    .venv/bin/python benchmarks/real_fixture.py    # needs ms3d-work/real-cases/ccstreet-zero (real_cases.py)
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from real_cases import LANE, SOURCES, build_zero_defect

from storage.formats.meshes import read_mesh

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "tests" / "data" / "ccstreet_crop"
BOX = ((31.0, 37.0), (16.0, 30.0), 13.5)

README = """# ccstreet_crop: a real ContextCapture production, cropped

A crop of a real photogrammetric reality mesh (Bentley ContextCapture, 3MXB with OpenCTM geometry) from the
GitHub repository `ProjSEED/Unity-3mx` (commit {commit}, `Assets/StreamingAssets/`), MIT licence
(`LICENSE` beside this file, copyright (c) 2020 GaoXing); the repository does not say where or by whom the
data was captured. Derived by `benchmarks/real_fixture.py`: the finest level of its node tree, ground moved to
z = 0, the faces with centroids in x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m, below {zmax:g} m: two facades facing a lane,
the ground and parked cars. {faces:,} faces, {vertices:,} vertices, {open_share:.1%} of the edges open after
welding coincident vertices (node borders, cracks: none of it a defect). Used by
`tests/tasks/classify/test_real_production.py`.
"""


def derive(out: Path = OUT) -> dict:
    case = build_zero_defect(ROOT / "ms3d-work" / "real-cases" / "ccstreet-zero", source="ccstreet")
    doc = json.loads((case / "case.json").read_text())
    m = read_mesh(case / "mesh.ply")
    v, f = np.asarray(m.vertices) - np.asarray(doc["world_origin"]), np.asarray(m.faces)
    c = v[f].mean(axis=1)
    (x0, x1), (y0, y1), zmax = BOX
    keep = (c[:, 0] >= x0) & (c[:, 0] < x1) & (c[:, 1] >= y0) & (c[:, 1] < y1) & (c[:, 2] < zmax)
    used, inv = np.unique(f[keep], return_inverse=True)
    vv, ff = v[used], inv.reshape(-1, 3)
    origin = np.floor(vv.min(axis=0))
    mm = np.round((vv - origin) * 1000.0)
    assert mm.max() < 32767 and len(vv) < 65536
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "mesh.npz", vertices_mm=mm.astype(np.int16), faces=ff.astype(np.uint16),
                        origin_m=origin, lane_m=np.asarray(LANE, np.float64))
    src = SOURCES["ccstreet"]
    commit = subprocess.run(["git", "--git-dir", str(src.mirror), "rev-parse", "HEAD"], capture_output=True,
                            text=True, check=True).stdout.strip()
    lic = subprocess.run(["git", "--git-dir", str(src.mirror), "show", "HEAD:LICENSE"], capture_output=True,
                         check=True).stdout
    (out / "LICENSE").write_bytes(lic)
    _, winv = np.unique(np.round(vv, 4), axis=0, return_inverse=True)
    w = winv.reshape(-1)[ff]
    edges = np.sort(np.concatenate([w[:, [0, 1]], w[:, [1, 2]], w[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    facts = {"faces": len(ff), "vertices": len(vv), "open_share": float((counts == 1).mean()), "commit": commit,
             "x0": x0, "x1": x1, "y0": y0, "y1": y1, "zmax": zmax}
    (out / "README.md").write_text(README.format(**facts))
    return facts | {"bytes": (out / "mesh.npz").stat().st_size}


if __name__ == "__main__":
    print(json.dumps(derive(), indent=1))
