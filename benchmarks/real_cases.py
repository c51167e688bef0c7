"""Benchmark cases built from real photogrammetric meshes: the zero-defect case.

The source is fetched, never committed: the Sceaux castle MVS mesh of ``cdcseacave/openMVS_sample``
(AGPL-3.0 repository, photos by P. Moulon for research use). Bring it here with the search tool's
``fetch`` (``github:cdcseacave/openMVS_sample``); this script reads ``scene_mesh_refine.ply`` from that
bare git folder (``git show``) and builds a case folder::

    mesh.ply                 the real mesh, metres, EPSG:2154 world coordinates (float64), z up
    mls/pass_000.laz, ...    an MLS scan ray-cast from a street in front of the facade (synth.mls:
                             VMX-450-like heads, occlusion by the mesh itself, 5 mm range noise,
                             trajectory error, density falling with range), EPSG:2154
    truth/truth_mesh.ply     the same mesh as the truth (zero-defect case: the scan agrees with it),
    truth/truth_mesh_faces.npz  per-face class from the normal (ground / wall / roof), and
    truth/registration.json  the frame origin, so ``report.quality`` measures the merged model against it
    case.json                source, licence, scale factor and how it was chosen, the frame, scan stats
    truth/defects.json       no defects: every patch is labelled good (``ms3d evaluate`` counts false alarms)
    campus.yaml              an ``ms3d run`` config (labels: that empty defects.json)

The MVS frame is arbitrary (SfM scale and orientation). :func:`upright` finds it: the facade plane is the
least principal axis of the area-weighted faces, turned to face the cameras (the mean face normal); "up"
is the in-plane axis along which the ground comes forward and the roof goes back. The scale is not a
documented dimension: no published height of this facade was found quickly, so the scale makes the wall
faces' height (2nd to 98th percentile) a plausible ``FACADE_HEIGHT_M`` = 15 m (stated in case.json).

    .venv/bin/python benchmarks/real_cases.py --out ms3d-work/real-cases/sceaux
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import laspy
import numpy as np
import yaml

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from storage.formats.meshes import read_mesh
from storage.formats.ply import write_ply
from storage.formats.points import LasChunkWriter, PointChunk
from synth.frames import asprs_classes
from synth.mls import MlsParams, simulate_mls, with_density
from synth.scene import FaceClass, Mesh, Scene
from synth.trajectory import TrajectoryParams, build_trajectories
from tasks.geometry.distance import MeshDistance

ROOT = Path(__file__).resolve().parents[1]
SOURCE_REPO = "cdcseacave/openMVS_sample"
SOURCE_FILE = "scene_mesh_refine.ply"
DEFAULT_MIRROR = Path("/work/.mirror/cdcseacave+openMVS_sample/repo")
CRS = "EPSG:2154"  # RGF93 / Lambert-93
WORLD_ORIGIN = (650_000.0, 6_857_000.0, 60.0)  # near Sceaux (Hauts-de-Seine); z: ground about 60 m
FACADE_HEIGHT_M = 15.0
CASE_VERSION = 3  # 3: labelled, every patch good


def read_source(mirror: Path, name: str = SOURCE_FILE, cache: Path | None = None) -> Path:
    """The source PLY copied out of the fetched bare git folder ``mirror`` (to ``cache``); a Git LFS pointer
    or a missing file is an error saying so (the case cannot be built then)."""
    out = (cache or Path("/tmp")) / name
    if out.exists() and out.stat().st_size > 1000:
        return out
    r = subprocess.run(["git", "--git-dir", str(mirror), "show", f"HEAD:{name}"], capture_output=True, check=False)
    if r.returncode != 0:
        raise SystemExit(f"{mirror}: {name} not in the fetched repository ({r.stderr.decode().strip()}); "
                         f"fetch github:{SOURCE_REPO} first")
    if r.stdout.startswith(b"version https://git-lfs"):
        raise SystemExit(f"{mirror}: {name} is a Git LFS pointer, not the mesh")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(r.stdout)
    return out


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


def face_classes(v: np.ndarray, f: np.ndarray, z_ground: float, height: float) -> np.ndarray:
    """(m,) uint8 FaceClass from the normal: up-facing faces low down are ground, high up roof, others wall."""
    c, n, _ = _face_geometry(v, f)
    cls = np.full(len(f), int(FaceClass.WALL), np.uint8)
    flat = n[:, 2] > 0.7
    cls[flat & (c[:, 2] < z_ground + 0.3 * height)] = int(FaceClass.GROUND)
    cls[(n[:, 2] > 0.4) & (c[:, 2] >= z_ground + 0.3 * height)] = int(FaceClass.ROOF)
    return cls


def metric_mesh(src: Path, facade_height_m: float = FACADE_HEIGHT_M) -> tuple[np.ndarray, np.ndarray, dict]:
    """The source mesh upright, scaled to metres, facade plane at y = 0, ground at z = 0, centred in x:
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
            "ground_faces_found": int(ground.sum()),
            "extent_m": np.round(local.max(0) - local.min(0), 3).tolist()}
    return local, f, info


def scan(local: np.ndarray, faces: np.ndarray, cls: np.ndarray, street_m: float, seed: int) -> tuple[Scene, list]:
    """The scene and trajectories of a street ``street_m`` in front of the facade (y = -street_m), two passes."""
    mesh = Mesh(local, faces, cls, np.zeros(len(faces), np.int32), np.full((len(faces), 3), 180, np.uint8))
    x0, x1 = local[:, 0].min() - 15.0, local[:, 0].max() + 15.0
    road = np.array([[x0, -street_m], [x1, -street_m]])
    scene = Scene(truth=mesh, occluders=None, buildings=[], roads=[road],
                  extent=(x0, -street_m - 10.0, x1, float(local[:, 1].max())))
    trajs = build_trajectories([road], TrajectoryParams(), np.random.default_rng(seed), truth=None)
    return scene, trajs


def write_scan(out: Path, scene, trajs, density: float, seed: int) -> dict:
    """One LAZ per pass under ``out/mls``, world coordinates in EPSG:2154; returns scan stats."""
    params = with_density(MlsParams.vmx450(), density)
    origin, rng = np.asarray(WORLD_ORIGIN), np.random.default_rng(seed + 1)
    stats = {"rays": 0, "points": 0, "passes": len(trajs), "density_scale": density}
    (out / "mls").mkdir(parents=True, exist_ok=True)
    for traj in trajs:
        with LasChunkWriter(out / "mls" / f"pass_{traj.traj_id:03d}.laz", crs=CRS,
                            offset=np.round(origin / 1000) * 1000) as w:
            for ch in simulate_mls(scene, [traj], params, rng):
                stats["rays"] += ch.n_rays
                if len(ch):
                    w.write(PointChunk(xyz=ch.xyz + origin, rgb=ch.rgb, intensity=ch.intensity,
                                       gps_time=ch.gps_time,
                                       classification=asprs_classes(ch.source, ch.face_class)))
                    stats["points"] += len(ch)
    return stats


def scan_agreement(out: Path, world: np.ndarray, faces: np.ndarray, n: int = 200_000) -> dict:
    """Distances (m) of up to ``n`` scan points (evenly taken) to the mesh: does the scan agree with it?"""
    pts = np.concatenate([laspy.read(p).xyz for p in sorted((out / "mls").glob("*.laz"))])
    pts = pts[:: max(1, len(pts) // n)]
    d, _ = MeshDistance(world, faces).query(pts)
    q = np.percentile(d, [50.0, 95.0, 99.0])
    return {"scan_to_mesh_median_m": round(float(q[0]), 4), "scan_to_mesh_p95_m": round(float(q[1]), 4),
            "scan_to_mesh_p99_m": round(float(q[2]), 4), "scan_within_5cm": round(float((d <= 0.05).mean()), 4)}


def write_campus_yaml(out: Path, name: str) -> None:
    """campus.yaml: the mesh and the scan are co-registered in EPSG:2154 (registration off); the labels are
    ``truth/defects.json`` without a defect (every patch good)."""
    cfg = {"name": name, "work_dir": f"../../{name}-work",
           "inputs": {"mesh": ["mesh.ply"], "points": ["mls"], "crs": CRS, "labels": "truth/defects.json"},
           "registration": {"mode": "off"}}
    (out / "campus.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))


def case_key(street_m: float, density: float, seed: int) -> dict:
    return {"version": CASE_VERSION, "source": f"{SOURCE_REPO}:{SOURCE_FILE}", "street_m": street_m,
            "mls_density_scale": density, "seed": seed, "facade_height_m": FACADE_HEIGHT_M}


def build_zero_defect(out: Path, mirror: Path = DEFAULT_MIRROR, street_m: float = 12.0, density: float = 0.25,
                      seed: int = 0, force: bool = False) -> Path:
    """Build (or reuse, when its case.json has the same key) the Sceaux zero-defect case in ``out``."""
    out = Path(out)
    key = case_key(street_m, density, seed)
    meta = out / "case.json"
    if not force and meta.exists() and json.loads(meta.read_text()).get("key") == key:
        return out
    t0 = time.perf_counter()
    src = read_source(mirror, cache=out / "source")
    local, faces, info = metric_mesh(src)
    cls = face_classes(local, faces, 0.0, FACADE_HEIGHT_M)
    world = local + np.asarray(WORLD_ORIGIN)
    (out / "truth").mkdir(parents=True, exist_ok=True)
    write_ply(out / "mesh.ply", world, faces)
    write_ply(out / "truth" / "truth_mesh.ply", world, faces)
    np.savez_compressed(out / "truth" / "truth_mesh_faces.npz", face_class=cls)
    (out / "truth" / "registration.json").write_text(json.dumps(
        {"frame_origin": list(WORLD_ORIGIN), "crs": CRS, "matrix_mls_to_mesh": np.eye(4).tolist(),
         "note": "zero-defect real-mesh case: the scan is simulated from the truth mesh, co-registered"}))
    (out / "truth" / "defects.json").write_text(json.dumps({"frame_origin": list(WORLD_ORIGIN), "defects": []}))
    scene, trajs = scan(local, faces, cls, street_m, seed)
    stats = write_scan(out, scene, trajs, density, seed)
    stats.update(scan_agreement(out, world, faces))
    write_campus_yaml(out, "real-sceaux-zero")
    _, _, area = _face_geometry(local, faces)
    doc = {"key": key, "case": "zero-defect", "mesh": "Sceaux castle MVS mesh (OpenMVS sample)",
           "source": {"repository": f"github:{SOURCE_REPO}", "file": SOURCE_FILE,
                      "licence": "AGPL-3.0 repository; photos (c) P. Moulon, research use; nothing committed"},
           "crs": CRS, "world_origin": list(WORLD_ORIGIN), **info,
           "faces": len(faces), "area_m2": round(float(area.sum()), 3),
           "face_classes": {c.name.lower(): int((cls == int(c)).sum()) for c in FaceClass if (cls == int(c)).any()},
           "scan": {**stats, "street_y_m": -street_m, "lane_offset_m": TrajectoryParams().lane_offset_m,
                    "speed_m_s": TrajectoryParams().speed_m_s, "scanner": "synth.mls MlsParams.vmx450"},
           "seconds": round(time.perf_counter() - t0, 1)}
    meta.write_text(json.dumps(doc, indent=1))
    return out


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "ms3d-work" / "real-cases" / "sceaux-zero")
    ap.add_argument("--mirror", type=Path, default=DEFAULT_MIRROR, help="bare git folder of the fetched source")
    ap.add_argument("--street-m", type=float, default=12.0, help="road centre line distance from the facade")
    ap.add_argument("--mls-density", type=float, default=0.25, help="synth.mls density_scale")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--force", action="store_true")
    a = ap.parse_args(argv)
    out = build_zero_defect(a.out, a.mirror, a.street_m, a.mls_density, a.seed, a.force)
    print(json.dumps({k: v for k, v in json.loads((out / "case.json").read_text()).items()
                      if k != "rotation_mvs_to_upright"}, indent=1))


if __name__ == "__main__":
    main()
