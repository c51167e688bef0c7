"""The Amsterdam street-LiDAR case: a real mobile scan and the 3DBAG LoD2.2 model of the same building.

The source is fetched, never committed: ``3DBAG/underpass-detection-experiments`` (Apache-2.0 repository;
3DBAG data CC BY 4.0). Bring it here with the search tool's ``fetch``
(``github:3DBAG/underpass-detection-experiments``); this script reads from that bare git folder:

- ``height_from_streetlidar/data/beemsterstraat/NL.IMBAG.Pand.<id>.laz``: a street-level mobile LiDAR crop
  around one building (LAS 1.4, point format 7, RGB, classes 1/2/3, GPS time, no CRS VLR), EPSG:7415
  (RD New + NAP heights);
- ``modelling_3d/sample_data/9-444-728_sm.city.jsonl``: CityJSONSeq of two 3DBAG buildings, one of them the
  same building (``NL.IMBAG.Pand.0363100012137139``).

It writes a case folder::

    mesh.ply        the building's finest LoD (2.2) solid, its polygons ear-clipped to triangles, EPSG:7415
    mls/scan.laz    the LiDAR crop as fetched
    campus.yaml     ``ms3d run`` config: co-registered (registration off), EPSG:7415, no labels
    case.json       source, licence, counts

A city model is coarse and lacks what the scan sees (the passage under the building, the ground, the street
furniture): the run's ``report.html`` measures the held-out scan strips against the input model and the merged
one (``quality.holdout_share``). ::

    .venv/bin/python benchmarks/amsterdam_case.py --out ms3d-work/real-cases/amsterdam
    .venv/bin/ms3d run ms3d-work/real-cases/amsterdam/campus.yaml --set runner=inline
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from storage.formats.ply import write_ply

ROOT = Path(__file__).resolve().parents[1]
SOURCE_REPO = "3DBAG/underpass-detection-experiments"
DEFAULT_MIRROR = Path("/work/.mirror/3DBAG+underpass-detection-experiments/repo")
BUILDING = "NL.IMBAG.Pand.0363100012137139"
LAZ = f"height_from_streetlidar/data/beemsterstraat/{BUILDING}.laz"
CITYJSON = "modelling_3d/sample_data/9-444-728_sm.city.jsonl"
CRS = "EPSG:7415"


def git_show(mirror: Path, name: str) -> bytes:
    """A file of the fetched bare repository; a missing one is an error saying to fetch it."""
    r = subprocess.run(["git", "--git-dir", str(mirror), "show", f"HEAD:{name}"], capture_output=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"{mirror}: {name} not in the fetched repository; fetch github:{SOURCE_REPO} first")
    return r.stdout


def ear_clip(poly: np.ndarray) -> np.ndarray:
    """Triangles (m, 3) of indices into a simple planar polygon ``poly`` (n, 3), by ear clipping in the
    polygon's plane (Newell normal). Collinear vertices are clipped as zero-area ears and dropped.

    >>> ear_clip(np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [1, 1, 0], [0, 2, 0]], float)).tolist()
    [[1, 2, 3], [0, 1, 3], [0, 3, 4]]
    """
    n = np.zeros(3)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        n += np.cross(a, b)
    k = int(np.argmax(np.abs(n)))
    xy = np.delete(poly, k, axis=1).astype(np.float64)
    if (n[k] >= 0) == (k == 1):  # dropping y reverses the orientation; make the polygon counter-clockwise
        xy[:, 0] = -xy[:, 0]
    idx = list(range(len(poly)))
    tris = []

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3 and guard < 10 * len(poly) ** 2:
        guard += 1
        for j in range(len(idx)):
            i0, i1, i2 = idx[j - 1], idx[j], idx[(j + 1) % len(idx)]
            a, b, c = xy[i0], xy[i1], xy[i2]
            turn = cross(a, b, c)
            if turn < 0:
                continue  # a reflex corner
            others = [m for m in idx if m not in (i0, i1, i2)]
            inside = any(cross(a, b, xy[m]) >= 0 and cross(b, c, xy[m]) >= 0 and cross(c, a, xy[m]) >= 0
                         for m in others) if turn > 0 else False
            if inside:
                continue
            if turn > 0:
                tris.append([i0, i1, i2])
            idx.pop(j)
            break
        else:
            break  # no ear: not simple; the rest is left out
    if len(idx) == 3 and cross(xy[idx[0]], xy[idx[1]], xy[idx[2]]) > 0:
        tris.append(idx)
    return np.asarray(tris, np.int64).reshape(-1, 3)


def building_mesh(seq: bytes, building: str = BUILDING) -> tuple[np.ndarray, np.ndarray, dict]:
    """(vertices (n, 3) world float64, faces (m, 3), info) of the building's finest LoD in a CityJSONSeq."""
    lines = [json.loads(x) for x in seq.decode().splitlines() if x.strip()]
    head, feats = lines[0], lines[1:]
    scale, shift = np.asarray(head["transform"]["scale"]), np.asarray(head["transform"]["translate"])
    feat = next((f for f in feats if f.get("id") == building), None)
    if feat is None:
        raise SystemExit(f"{building} not in the CityJSONSeq")
    verts = np.asarray(feat["vertices"], np.float64) * scale + shift
    best = None
    for obj in feat["CityObjects"].values():
        for g in obj.get("geometry", []):
            if best is None or float(g.get("lod", 0)) > float(best.get("lod", 0)):
                best = g
    faces, inner_rings, untriangulated = [], 0, 0
    shells = best["boundaries"] if best["type"] == "Solid" else [best["boundaries"]]
    for shell in shells:
        for surface in shell:
            ring = np.asarray(surface[0], np.int64)  # outer ring; inner rings (rare on LoD2.2) are left out, counted
            inner_rings += len(surface) - 1
            tris = ear_clip(verts[ring])
            untriangulated += int(len(tris) == 0)
            faces += [ring[t] for t in tris]
    faces = np.asarray(faces, np.int64)
    used, inv = np.unique(faces, return_inverse=True)
    info = {"lod": best.get("lod"), "geometry": best["type"], "surfaces": sum(len(s) for s in shells),
            "triangles": len(faces), "inner_rings_left_out": inner_rings, "surfaces_not_triangulated": untriangulated,
            "crs": head.get("metadata", {}).get("referenceSystem")}
    return verts[used], inv.reshape(-1, 3), info


def build_case(out: Path, mirror: Path = DEFAULT_MIRROR) -> Path:
    out = Path(out)
    (out / "mls").mkdir(parents=True, exist_ok=True)
    (out / "mls" / "scan.laz").write_bytes(git_show(mirror, LAZ))
    v, f, info = building_mesh(git_show(mirror, CITYJSON))
    write_ply(out / "mesh.ply", v, f)
    cfg = {"name": "amsterdam-beemsterstraat", "work_dir": "../../amsterdam-work",
           "inputs": {"mesh": ["mesh.ply"], "points": ["mls"], "crs": CRS}, "registration": {"mode": "off"}}
    (out / "campus.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
    doc = {"case": "real co-registered pair: street LiDAR and a 3DBAG LoD2.2 model", "building": BUILDING,
           "source": {"repository": f"github:{SOURCE_REPO}", "files": [LAZ, CITYJSON],
                      "licence": "Apache-2.0 repository; 3DBAG CC BY 4.0; nothing committed"},
           "crs": CRS, "mesh": info, "extent_m": np.round(v.max(0) - v.min(0), 2).tolist()}
    (out / "case.json").write_text(json.dumps(doc, indent=1))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "ms3d-work" / "real-cases" / "amsterdam")
    ap.add_argument("--mirror", type=Path, default=DEFAULT_MIRROR)
    a = ap.parse_args(argv)
    print(json.dumps(json.loads((build_case(a.out, a.mirror) / "case.json").read_text()), indent=1))


if __name__ == "__main__":
    main()
