"""An MLS scan of any mesh: the synth scanner (:mod:`synth.mls`) driven along a street past a given mesh (a
real production, a crop of one), which is both the scene and the truth. The scan agrees with the mesh by
construction, so a grader that calls the mesh bad there is wrong.

- :func:`face_classes`: ground / wall / roof per face from its normal and height;
- :func:`write_mesh_scan`: one LAZ per pass of a vehicle along a road polyline (VMX-450-like heads,
  occlusion by the mesh itself, range noise, trajectory error, density falling with range), world
  coordinates in a CRS; returns the scan's counts.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.formats.points import LasChunkWriter, PointChunk

from .frames import asprs_classes
from .mls import MlsParams, simulate_mls, with_density
from .scene import FaceClass, Mesh, Scene
from .trajectory import TrajectoryParams, build_trajectories


def face_classes(v: np.ndarray, f: np.ndarray, z_ground: float, height: float) -> np.ndarray:
    """(m,) uint8 :class:`FaceClass` of faces f (m, 3) of vertices v (n, 3) (metres, z up): up-facing faces in
    the lowest 30 % of ``height`` above ``z_ground`` are ground, up-facing ones above it roof, others wall."""
    t = np.asarray(v, np.float64)[np.asarray(f)]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n = n / np.maximum(np.linalg.norm(n, axis=1), 1e-30)[:, None]
    cz = t[:, :, 2].mean(axis=1)
    cls = np.full(len(t), int(FaceClass.WALL), np.uint8)
    cls[(n[:, 2] > 0.7) & (cz < z_ground + 0.3 * height)] = int(FaceClass.GROUND)
    cls[(n[:, 2] > 0.4) & (cz >= z_ground + 0.3 * height)] = int(FaceClass.ROOF)
    return cls


def mesh_scene(v: np.ndarray, f: np.ndarray, cls: np.ndarray, road: np.ndarray, seed: int) -> tuple[Scene, list]:
    """The scene (the mesh as its truth, no occluders) and two passes of a vehicle along ``road`` (k, 2)."""
    mesh = Mesh(np.asarray(v, np.float64), np.asarray(f, np.int64), cls, np.zeros(len(f), np.int32),
                np.full((len(f), 3), 180, np.uint8))
    road = np.asarray(road, np.float64)
    lo = np.minimum(mesh.vertices[:, :2].min(0), road.min(0)) - 10.0
    hi = np.maximum(mesh.vertices[:, :2].max(0), road.max(0)) + 10.0
    scene = Scene(truth=mesh, occluders=None, buildings=[], roads=[road], extent=(lo[0], lo[1], hi[0], hi[1]))
    return scene, build_trajectories([road], TrajectoryParams(), np.random.default_rng(seed), truth=None)


def write_mesh_scan(out: Path, v: np.ndarray, f: np.ndarray, cls: np.ndarray, road: np.ndarray, density: float,
                    seed: int, crs: str, world_origin) -> dict:
    """Scan the mesh (v (n, 3) local metres, f (m, 3), cls (m,)) from a vehicle along ``road`` (k, 2) into
    ``out/pass_{k:03d}.laz`` (world = local + ``world_origin``, in ``crs``) at ``density`` times the
    VMX-450's rate. Returns {"rays", "points", "passes", "density_scale"}."""
    scene, trajs = mesh_scene(v, f, cls, road, seed)
    params = with_density(MlsParams.vmx450(), density)
    origin, rng = np.asarray(world_origin, np.float64), np.random.default_rng(seed + 1)
    stats = {"rays": 0, "points": 0, "passes": len(trajs), "density_scale": density}
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    for traj in trajs:
        with LasChunkWriter(out / f"pass_{traj.traj_id:03d}.laz", crs=crs, offset=np.round(origin / 1000) * 1000) as w:
            for ch in simulate_mls(scene, [traj], params, rng):
                stats["rays"] += ch.n_rays
                if len(ch):
                    w.write(PointChunk(xyz=ch.xyz + origin, rgb=ch.rgb, intensity=ch.intensity, gps_time=ch.gps_time,
                                       classification=asprs_classes(ch.source, ch.face_class)))
                    stats["points"] += len(ch)
    return stats


__all__ = ["face_classes", "mesh_scene", "write_mesh_scan"]
