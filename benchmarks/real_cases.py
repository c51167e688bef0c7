"""Benchmark cases built from real photogrammetric meshes: the zero-defect case of each real source.

The sources are fetched, never committed (:data:`SOURCES`; bring each with the search tool's ``fetch``):

- ``sceaux``: the Sceaux castle MVS mesh of ``cdcseacave/openMVS_sample`` (``scene_mesh_refine.ply``;
  AGPL-3.0 repository, photos by P. Moulon for research use). An OpenMVS reconstruction in an arbitrary
  SfM frame: :func:`upright` finds it (the facade plane is the least principal axis of the area-weighted
  faces, turned to face the cameras; "up" is the in-plane axis along which the ground comes forward and the
  roof goes back), and the scale is not a documented dimension: it makes the wall faces' height (2nd to 98th
  percentile) a plausible ``FACADE_HEIGHT_M`` = 15 m (stated in case.json). The street runs along the
  facade, ``--street-m`` in front of it.
- ``ccstreet``: a ContextCapture production in 3MXB (``ProjSEED/Unity-3mx``, ``Assets/StreamingAssets``:
  410 node files, 383,015 finest-level triangles, 159 photo textures; MIT licence of the repository, the
  data's origin unstated): a street corner with two building rows, a lane with parked cars between them,
  roofs. Not watertight: its 159 leaf nodes are not stitched (case.json counts the open edges after welding). Its
  local frame is metres with z up (storeys ~3 m, cars ~4.5 m), so it is only moved: ground to z = 0. The
  scan drives along the lane between the two facades (``LANE``), both ways.

Each case folder::

    mesh.ply                 the real mesh, metres, world coordinates in the case's CRS (float64), z up
    mls/pass_000.laz, ...    an MLS scan ray-cast from the street (synth.mls: VMX-450-like heads, occlusion
                             by the mesh itself, 5 mm range noise, trajectory error, density falling with
                             range), world coordinates
    truth/truth_mesh.ply     the same mesh as the truth (zero-defect case: the scan agrees with it),
    truth/truth_mesh_faces.npz  per-face class from the normal (ground / wall / roof), and
    truth/registration.json  the frame origin, so ``report.quality`` measures the merged model against it
    case.json                source, licence, scale factor and how it was chosen, the frame, scan stats
    truth/defects.json       no defects: every patch is labelled good (``ms3d evaluate`` counts false alarms)
    campus.yaml              an ``ms3d run`` config (labels: that empty defects.json)

    .venv/bin/python benchmarks/real_cases.py --source sceaux --out ms3d-work/real-cases/sceaux-zero
    .venv/bin/python benchmarks/real_cases.py --source ccstreet --out ms3d-work/real-cases/ccstreet-zero
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import laspy
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from storage.formats.meshes import read_mesh
from storage.formats.ply import write_ply
from synth.scan_mesh import face_classes, write_mesh_scan
from synth.scene import FaceClass
from synth.trajectory import TrajectoryParams
from tasks.geometry.distance import MeshDistance

ROOT = Path(__file__).resolve().parents[1]
FACADE_HEIGHT_M = 15.0
CASE_VERSION = 3  # 3: labelled, every patch good


@dataclass(frozen=True)
class RealSource:
    """A real mesh to build cases from. repo: GitHub owner/name (fetched bare under /work/.mirror); paths: what
    to take out of it (a file or a folder); entry: the file ms3d reads, relative to the extracted copy; crs and
    world_origin: where the case is placed (float64 metres); road: the street polyline's name (:func:`road_of`)."""

    name: str
    title: str
    repo: str
    paths: tuple[str, ...]
    entry: str
    licence: str
    crs: str
    world_origin: tuple[float, float, float]
    frame: str  # "mvs": arbitrary SfM frame (upright + scale); "metric": metres, z up (ground to 0 only)

    @property
    def mirror(self) -> Path:
        return Path("/work/.mirror") / self.repo.replace("/", "+") / "repo"


SOURCES = {
    "sceaux": RealSource(
        "sceaux", "Sceaux castle MVS mesh (OpenMVS sample)", "cdcseacave/openMVS_sample",
        ("scene_mesh_refine.ply",), "scene_mesh_refine.ply",
        "AGPL-3.0 repository; photos (c) P. Moulon, research use; nothing committed", "EPSG:2154",
        (650_000.0, 6_857_000.0, 60.0), "mvs"),  # near Sceaux (Hauts-de-Seine); z: ground about 60 m
    "ccstreet": RealSource(
        "ccstreet", "ContextCapture 3MXB street corner (ProjSEED/Unity-3mx)", "ProjSEED/Unity-3mx",
        ("Assets/StreamingAssets",), "Assets/StreamingAssets/root.3mxb",
        "MIT (repository LICENSE, (c) 2020 GaoXing); the data's origin is not stated; nothing committed",
        "EPSG:32650", (589_000.0, 2_712_000.0, 15.0), "metric"),  # an arbitrary UTM 50N placement
}
SOURCE_REPO, SOURCE_FILE = SOURCES["sceaux"].repo, SOURCES["sceaux"].entry  # the first source's (older callers)
DEFAULT_MIRROR = SOURCES["sceaux"].mirror
CRS, WORLD_ORIGIN = SOURCES["sceaux"].crs, SOURCES["sceaux"].world_origin
# the lane of ``ccstreet`` (local metres after its ground shift): between the facades facing it at y ~ 19.5
# (+y normals) and y ~ 28.3 (-y normals), open ground and parked cars from x ~ 26 east beyond the capture
LANE = ((26.5, 24.0), (52.0, 24.0))


def read_source(mirror: Path, name: str = SOURCE_FILE, cache: Path | None = None) -> Path:
    """The source file or folder ``name`` copied out of the fetched bare git folder ``mirror`` (to ``cache``);
    a Git LFS pointer or a missing path is an error saying so (the case cannot be built then)."""
    out = (cache or Path("/tmp")) / name
    if out.exists() and (out.is_dir() or out.stat().st_size > 1000):
        return out
    git = ["git", "--git-dir", str(mirror)]
    kind = subprocess.run(git + ["cat-file", "-t", f"HEAD:{name}"], capture_output=True, check=False)
    if kind.returncode != 0:
        raise SystemExit(f"{mirror}: {name} not in the fetched repository ({kind.stderr.decode().strip()}); "
                         f"fetch the source repository first")
    if kind.stdout.strip() == b"tree":
        listing = subprocess.run(git + ["ls-tree", "-r", "--name-only", "HEAD", name], capture_output=True, check=True)
        for rel in listing.stdout.decode().splitlines():
            if rel.endswith(".meta"):
                continue  # Unity's sidecar files
            _git_file(git, rel, (cache or Path("/tmp")) / rel, mirror)
        return out
    _git_file(git, name, out, mirror)
    return out


def _git_file(git: list[str], rel: str, out: Path, mirror: Path) -> None:
    r = subprocess.run(git + ["show", f"HEAD:{rel}"], capture_output=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"{mirror}: {rel} not readable ({r.stderr.decode().strip()})")
    if r.stdout.startswith(b"version https://git-lfs"):
        raise SystemExit(f"{mirror}: {rel} is a Git LFS pointer, not the mesh")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(r.stdout)


def _face_geometry(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centroids (m, 3), unit normals (m, 3), areas (m,)) of a triangle mesh."""
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    a = np.linalg.norm(n, axis=1)
    return t.mean(1), n / np.maximum(a, 1e-30)[:, None], 0.5 * a


def upright(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """A rotation R (3, 3) taking the MVS frame to one with z up and the facade facing -y (rows: x, y, z)."""
    c, n, a = _face_geometry(v, f)
    mean = np.average(c, axis=0, weights=a)
    cov = np.cov((c - mean).T, aweights=a)
    _, vec = np.linalg.eigh(cov)  # ascending: vec[:, 0] the facade normal, vec[:, 2] along the facade
    normal = vec[:, 0] * (1.0 if np.sum(a[:, None] * n, axis=0) @ vec[:, 0] >= 0 else -1.0)
    wall = np.abs(n @ normal) > np.cos(np.radians(30.0))
    normal = np.average(n[wall] * np.sign(n[wall] @ normal)[:, None], axis=0, weights=a[wall])
    normal /= np.linalg.norm(normal)
    up = vec[:, 1] - (vec[:, 1] @ normal) * normal
    up /= np.linalg.norm(up)
    depth, height = (c - mean) @ normal, (c - mean) @ up
    if np.cov(depth, height, aweights=a)[0, 1] > 0:  # ground comes forward at the bottom, roofs recede on top
        up = -up
    y = -normal
    return np.stack([np.cross(y, up), y, up])


def metric_mesh(src: Path, facade_height_m: float = FACADE_HEIGHT_M) -> tuple[np.ndarray, np.ndarray, dict]:
    """An MVS mesh upright, scaled to metres, facade plane at y = 0, ground at z = 0, centred in x:
    (vertices (n, 3) float64 local metres, faces (m, 3), info for case.json)."""
    m = read_mesh(src)
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    rot = upright(v, f)
    u = v @ rot.T
    c, n, _ = _face_geometry(u, f)
    wall = np.abs(n[:, 2]) < 0.5
    z_lo, z_hi = np.percentile(c[wall, 2], [2.0, 98.0])
    scale = facade_height_m / (z_hi - z_lo)
    ground = (n[:, 2] > 0.8) & (c[:, 2] < z_lo + 0.15 * (z_hi - z_lo))
    z0 = float(np.median(c[ground, 2])) if ground.sum() > 20 else float(z_lo)
    shift = np.array([-0.5 * (u[:, 0].min() + u[:, 0].max()), -float(np.median(c[wall, 1])), -z0])
    local = (u + shift) * scale
    info = {"rotation_mvs_to_upright": rot.round(6).tolist(), "scale_factor_m_per_unit": round(float(scale), 6),
            "scale_source": (f"not a documented dimension: scaled so that the wall faces' height (2nd-98th "
                             f"percentile of their centroids, {z_hi - z_lo:.4f} MVS units) is a plausible "
                             f"{facade_height_m:g} m for the Chateau de Sceaux main facade"),
            "ground_faces_found": int(ground.sum()), "height_m": facade_height_m,
            "extent_m": np.round(local.max(0) - local.min(0), 3).tolist()}
    return local, f, info


def grounded_mesh(src: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """A mesh already in metres with z up (a ContextCapture production's local frame), moved so its ground
    (the area-weighted median height of the up-facing faces in its lowest fifth) is z = 0: (vertices (n, 3)
    float64, faces (m, 3), info for case.json, with the open edges left after welding coincident vertices)."""
    m = read_mesh(src)
    v, f = np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)
    c, n, a = _face_geometry(v, f)
    lo, hi = np.percentile(c[:, 2], [1.0, 99.0])
    ground = (n[:, 2] > 0.8) & (c[:, 2] < lo + 0.2 * (hi - lo))
    order = np.argsort(c[ground, 2])
    cum = np.cumsum(a[ground][order])
    z0 = float(c[ground, 2][order][np.searchsorted(cum, 0.5 * cum[-1])])
    local = v - [0.0, 0.0, z0]
    _, inv = np.unique(np.round(v, 4), axis=0, return_inverse=True)  # weld coincident vertices (0.1 mm)
    welded = inv.reshape(-1)[f]
    edges = np.sort(np.concatenate([welded[:, [0, 1]], welded[:, [1, 2]], welded[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    info = {"scale_factor_m_per_unit": 1.0, "scale_source": "the production's own metres (storeys ~3 m, cars ~4.5 m)",
            "ground_shift_m": round(-z0, 3), "height_m": round(float(hi - z0), 2),
            "textures": len(m.textures),
            "edges_open_after_welding": round(float((counts == 1).sum() / len(counts)), 4),
            "extent_m": np.round(local.max(0) - local.min(0), 3).tolist()}
    return local, f, info


def road_of(source: RealSource, local: np.ndarray, street_m: float) -> np.ndarray:
    """(k, 2) the street polyline of a case (local metres): ``street_m`` in front of an MVS facade (y = 0,
    facing -y), or the source's lane."""
    if source.name == "ccstreet":
        return np.asarray(LANE, np.float64)
    x0, x1 = local[:, 0].min() - 15.0, local[:, 0].max() + 15.0
    return np.array([[x0, -street_m], [x1, -street_m]])


def scan_agreement(out: Path, world: np.ndarray, faces: np.ndarray, n: int = 200_000) -> dict:
    """Distances (m) of up to ``n`` scan points (evenly taken) to the mesh: does the scan agree with it?"""
    pts = np.concatenate([laspy.read(p).xyz for p in sorted((out / "mls").glob("*.laz"))])
    pts = pts[:: max(1, len(pts) // n)]
    d, _ = MeshDistance(world, faces).query(pts)
    q = np.percentile(d, [50.0, 95.0, 99.0])
    return {"scan_to_mesh_median_m": round(float(q[0]), 4), "scan_to_mesh_p95_m": round(float(q[1]), 4),
            "scan_to_mesh_p99_m": round(float(q[2]), 4), "scan_within_5cm": round(float((d <= 0.05).mean()), 4)}


def write_campus_yaml(out: Path, name: str, crs: str = CRS) -> None:
    """campus.yaml: the mesh and the scan are co-registered in ``crs`` (registration off); the labels are
    ``truth/defects.json`` without a defect (every patch good)."""
    cfg = {"name": name, "work_dir": f"../../{name}-work",
           "inputs": {"mesh": ["mesh.ply"], "points": ["mls"], "crs": crs, "labels": "truth/defects.json"},
           "registration": {"mode": "off"}}
    (out / "campus.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))


def case_key(street_m: float, density: float, seed: int, source: RealSource = SOURCES["sceaux"]) -> dict:
    key = {"version": CASE_VERSION, "source": f"{source.repo}:{source.entry}", "street_m": street_m,
           "mls_density_scale": density, "seed": seed, "facade_height_m": FACADE_HEIGHT_M}
    if source.name != "sceaux":  # the first source's key as it was (its built cases stay valid)
        key.update(road=np.round(road_of(source, np.zeros((1, 3)), street_m), 3).tolist(), frame=source.frame)
    return key


def build_zero_defect(out: Path, mirror: Path | None = None, street_m: float = 12.0, density: float = 0.25,
                      seed: int = 0, force: bool = False, source: str = "sceaux") -> Path:
    """Build (or reuse, when its case.json has the same key) the zero-defect case of ``source`` in ``out``."""
    src_def = SOURCES[source]
    mirror = src_def.mirror if mirror is None else Path(mirror)
    out = Path(out)
    key = case_key(street_m, density, seed, src_def)
    meta = out / "case.json"
    if not force and meta.exists() and json.loads(meta.read_text()).get("key") == key:
        return out
    t0 = time.perf_counter()
    for rel in src_def.paths:
        read_source(mirror, rel, cache=out / "source")
    src = out / "source" / src_def.entry
    local, faces, info = metric_mesh(src) if src_def.frame == "mvs" else grounded_mesh(src)
    cls = face_classes(local, faces, 0.0, info["height_m"])
    world = local + np.asarray(src_def.world_origin)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    write_ply(out / "mesh.ply", world, faces)
    write_ply(out / "truth" / "truth_mesh.ply", world, faces)
    np.savez_compressed(out / "truth" / "truth_mesh_faces.npz", face_class=cls)
    (out / "truth" / "registration.json").write_text(json.dumps(
        {"frame_origin": list(src_def.world_origin), "crs": src_def.crs, "matrix_mls_to_mesh": np.eye(4).tolist(),
         "note": "zero-defect real-mesh case: the scan is simulated from the truth mesh, co-registered"}))
    (out / "truth" / "defects.json").write_text(json.dumps({"frame_origin": list(src_def.world_origin), "defects": []}))
    road = road_of(src_def, local, street_m)
    stats = write_mesh_scan(out / "mls", local, faces, cls, road, density, seed, src_def.crs, src_def.world_origin)
    stats.update(scan_agreement(out, world, faces))
    write_campus_yaml(out, f"real-{source}-zero", src_def.crs)
    _, _, area = _face_geometry(local, faces)
    doc = {"key": key, "case": "zero-defect", "source_name": source, "mesh": src_def.title,
           "source": {"repository": f"github:{src_def.repo}", "file": src_def.entry, "licence": src_def.licence},
           "crs": src_def.crs, "world_origin": list(src_def.world_origin), **info,
           "faces": len(faces), "area_m2": round(float(area.sum()), 3),
           "face_classes": {c.name.lower(): int((cls == int(c)).sum()) for c in FaceClass if (cls == int(c)).any()},
           "scan": {**stats, "road_local_m": np.round(road, 3).tolist(), "street_y_m": float(road[0, 1]),
                    "lane_offset_m": TrajectoryParams().lane_offset_m,
                    "speed_m_s": TrajectoryParams().speed_m_s, "scanner": "synth.mls MlsParams.vmx450"},
           "seconds": round(time.perf_counter() - t0, 1)}
    meta.write_text(json.dumps(doc, indent=1))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--source", default="sceaux", choices=sorted(SOURCES))
    ap.add_argument("--out", type=Path, default=None, help="default: ms3d-work/real-cases/<source>-zero")
    ap.add_argument("--mirror", type=Path, default=None, help="bare git folder of the fetched source")
    ap.add_argument("--street-m", type=float, default=12.0, help="road centre line distance from the facade")
    ap.add_argument("--mls-density", type=float, default=0.25, help="synth.mls density_scale")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args(argv)
    out = a.out or ROOT / "ms3d-work" / "real-cases" / f"{a.source}-zero"
    out = build_zero_defect(out, a.mirror, a.street_m, a.mls_density, a.seed, a.force, a.source)
    print(json.dumps({k: v for k, v in json.loads((out / "case.json").read_text()).items()
                      if k != "rotation_mvs_to_upright"}, indent=1))


if __name__ == "__main__":
    main()
