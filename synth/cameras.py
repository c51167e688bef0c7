"""Vehicle cameras: pinhole images of the scene (truth + occluders) taken along the trajectories.

Convention (OpenCV): a world point X (mesh frame, metres) maps to camera coordinates
``x_c = R @ X + t`` (R: world-to-camera rotation, t = -R @ C for the camera centre C) with x right,
y down, z forward (the optical axis); pixel ``(u, v) = (fx x_c/z_c + cx, fy y_c/z_c + cy)``, u the
column and v the row, integer (u, v) at pixel *centres* (so pixel [row, col] covers
v in [row-0.5, row+0.5)). cx, cy = ((W-1)/2, (H-1)/2).

Cameras fire every ``every_m`` metres along each trajectory, one image per mount (left / right,
optionally forward-oblique). Images are rendered from the *true* pose; the pose written to
cameras.json is the *recorded* one (true + the trajectory error at that time), exactly as the
MLS points are shifted by the same error, so images and MLS agree and both disagree with the
mesh by the GNSS/INS error. Colour is the face colour x Lambert shading (sun + ambient),
double-sided; rays that hit nothing get the sky colour.
"""

from __future__ import annotations

import functools
import io
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from .raycast import SceneCaster
from .scene import Scene
from .trajectory import Trajectory


@dataclass(frozen=True)
class CameraMount:
    """A camera on the vehicle: yaw_deg counter-clockwise from the driving direction (left = +90),
    pitch_deg up from horizontal; position_m in the vehicle frame (x forward, y left, z up)."""

    name: str
    yaw_deg: float
    pitch_deg: float = 10.0
    position_m: tuple[float, float, float] = (0.0, 0.0, 2.3)


LEFT = CameraMount("left", 90.0)
RIGHT = CameraMount("right", -90.0)
FRONT_LEFT = CameraMount("frontleft", 45.0)
FRONT_RIGHT = CameraMount("frontright", -45.0)


@dataclass(frozen=True)
class CameraParams:
    width: int = 2048
    height: int = 1536
    hfov_deg: float = 90.0
    every_m: float = 5.0
    mounts: tuple[CameraMount, ...] = (LEFT, RIGHT)
    sky_rgb: tuple[int, int, int] = (175, 205, 235)
    sun_azimuth_deg: float = 135.0  # counter-clockwise from +x (east)
    sun_elevation_deg: float = 45.0
    ambient: float = 0.45  # skylight share: facades facing away from the sun stay readable
    apply_trajectory_error: bool = True
    image_ext: str = ".jpg"
    noise_dn: float = 2.0  # sensor noise (1 sigma, 8-bit counts), added only when an rng is given
    nthreads: int = 0

    @property
    def focal_px(self) -> float:
        return 0.5 * self.width / np.tan(np.radians(0.5 * self.hfov_deg))

    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsics."""
        f = self.focal_px
        return np.array([[f, 0.0, 0.5 * (self.width - 1)], [0.0, f, 0.5 * (self.height - 1)], [0.0, 0.0, 1.0]])


@dataclass
class Exposure:
    """One exposure of a vehicle camera: its recorded pinhole pose and when, on which trajectory and mount it
    fired. K: (3, 3); R: (3, 3) world-to-camera; t: (3,) metres (recorded pose); error_m: (3,) recorded
    minus true camera centre (not written to cameras.json). Its cameras.json entry (:meth:`to_json`) reads
    back as a :class:`storage.formats.cameras.Camera` (no distortion)."""

    image: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    timestamp: float  # GPS seconds of week
    traj_id: int
    mount: str
    error_m: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """(3,) recorded camera centre, mesh frame metres."""
        return -self.R.T @ self.t

    def to_json(self) -> dict:
        """The cameras.json entry: plain lists and numbers."""
        return {"image": self.image, "K": self.K.tolist(), "R": self.R.tolist(), "t": self.t.tolist(),
                "width": self.width, "height": self.height, "timestamp": self.timestamp}


def look_rotation(yaw_rad: float, pitch_rad: float) -> np.ndarray:
    """World-to-camera rotation (3, 3) for an optical axis at azimuth yaw (CCW from +x) and pitch
    (up), with no roll: rows are the camera x (right), y (down), z (forward) axes in the world."""
    z = np.array([np.cos(pitch_rad) * np.cos(yaw_rad), np.cos(pitch_rad) * np.sin(yaw_rad), np.sin(pitch_rad)])
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def place_cameras(trajectories: list[Trajectory], params: CameraParams = CameraParams()) -> list[Exposure]:
    """Exposures every ``params.every_m`` along each trajectory, for every mount, in time order
    per trajectory. Names: ``t{traj_id:03d}_{index:05d}_{mount}{image_ext}``."""
    cams = []
    K = params.K()
    for tr in trajectories:
        s = np.arange(0.0, tr.length_m, params.every_m)
        times = tr.t_start + s / tr.speed_m_s
        pos, heading = tr.pose_at(times)
        err = tr.error_at(times) if params.apply_trajectory_error else np.zeros((len(times), 3))
        for i, (p, h, e, ts) in enumerate(zip(pos, heading, err, times)):
            c, sn = np.cos(h), np.sin(h)
            for m in params.mounts:
                mx, my, mz = m.position_m
                centre = p + np.array([mx * c - my * sn, mx * sn + my * c, mz]) + e
                R = look_rotation(h + np.radians(m.yaw_deg), np.radians(m.pitch_deg))
                cams.append(Exposure(f"t{tr.traj_id:03d}_{i:05d}_{m.name}{params.image_ext}", K, R, -R @ centre,
                                   params.width, params.height, float(ts), tr.traj_id, m.name, e))
    return cams


def project(points: np.ndarray, cam: Exposure) -> tuple[np.ndarray, np.ndarray]:
    """Project world points (n, 3) float64 with the recorded pose.

    Returns uv (n, 2) float64 pixels (OpenCV convention above; pixel [round(v), round(u)]) and
    depth (n,) float64 metres along the optical axis (<= 0: behind the camera, uv meaningless).
    """
    xc = np.asarray(points, np.float64) @ cam.R.T + cam.t
    z = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = (xc[:, :2] / z[:, None]) @ cam.K[:2, :2].T + cam.K[:2, 2]
    return uv, z


@dataclass
class Render:
    """rgb: (H, W, 3) uint8; source: (H, W) int8 (0 truth, 1 occluder, -1 sky); face: (H, W) int64
    face index in its source mesh (-1 sky); depth: (H, W) float32 metres along the optical axis."""

    rgb: np.ndarray
    source: np.ndarray
    face: np.ndarray
    depth: np.ndarray


@functools.lru_cache(maxsize=4)
def _pixel_rays(k_key: tuple, w: int, h: int) -> np.ndarray:
    """Unit ray directions (h * w, 3) float32 in the camera frame through every pixel centre,
    row-major, with ``1 / |K^-1 (u, v, 1)|`` (the depth per unit range) in a 4th column."""
    kinv = np.linalg.inv(np.array(k_key).reshape(3, 3))
    v, u = np.mgrid[0:h, 0:w]
    d = np.stack([u.ravel(), v.ravel(), np.ones(h * w)], axis=1) @ kinv.T
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    return np.hstack([d / norm, 1.0 / norm]).astype(np.float32)


def render(caster: SceneCaster, cam: Exposure, params: CameraParams = CameraParams()) -> Render:
    """Ray cast every pixel of ``cam`` from its true pose (recorded centre minus ``cam.error_m``)."""
    h, w = cam.height, cam.width
    pix = _pixel_rays(tuple(cam.K.ravel()), w, h)
    rays = np.empty((h * w, 6), np.float32)
    rays[:, :3] = cam.centre - cam.error_m - caster.origin_m
    rays[:, 3:] = pix[:, :3] @ cam.R.astype(np.float32)  # rows: R^T d_cam
    hits = caster.cast_local(rays, params.nthreads)
    hit = np.flatnonzero(hits.source >= 0)
    row = caster.global_face(hits.source[hit], hits.face[hit])
    az, el = np.radians(params.sun_azimuth_deg), np.radians(params.sun_elevation_deg)
    sun = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    n = caster.all_face_normal[row]
    facing = np.sum(n * rays[hit, 3:], axis=1) > 0  # double-sided: use the side the ray sees
    lambert = np.abs(n @ sun) * ((n @ sun > 0) != facing)
    shade = params.ambient + (1.0 - params.ambient) * lambert
    rgb = np.empty((h * w, 3), np.uint8)
    rgb[:] = params.sky_rgb
    rgb[hit] = np.clip(np.round(caster.all_face_color[row] * shade[:, None]), 0, 255).astype(np.uint8)
    depth = np.full(h * w, np.inf, np.float32)
    depth[hit] = hits.t[hit] * pix[hit, 3]
    return Render(rgb=rgb.reshape(h, w, 3), source=hits.source.reshape(h, w),
                  face=hits.face.reshape(h, w), depth=depth.reshape(h, w))


def render_images(
    scene: Scene, cameras: list[Exposure], params: CameraParams = CameraParams()
) -> Iterator[tuple[Exposure, np.ndarray]]:
    """Yield (camera, rgb (H, W, 3) uint8) for each camera; one BVH is built for all of them."""
    caster = SceneCaster(scene.truth, scene.occluders.mesh if scene.occluders else None)
    for cam in cameras:
        yield cam, render(caster, cam, params).rgb


def render_cameras(
    scene: Scene,
    trajectories: list[Trajectory],
    every_m: float = 5.0,
    size: tuple[int, int] = (2048, 1536),
    rng: np.random.Generator | None = None,
    params: CameraParams = CameraParams(),
) -> tuple[Iterator[np.ndarray], list[Exposure]]:
    """Place cameras every ``every_m`` along the trajectories and render them lazily.

    size: (width, height) pixels, overriding ``params``. Returns (an iterator of rgb (H, W, 3)
    uint8 images, one per camera and in the same order - rendered when consumed, so memory holds
    one image at a time; the cameras). With ``rng``, Gaussian sensor noise of ``params.noise_dn``.
    """
    params = replace(params, every_m=every_m, width=int(size[0]), height=int(size[1]))
    cams = place_cameras(trajectories, params)

    def images():
        caster = SceneCaster(scene.truth, scene.occluders.mesh if scene.occluders else None)
        for cam in cams:
            rgb = render(caster, cam, params).rgb
            if rng is not None and params.noise_dn > 0:
                rgb = np.clip(rgb + rng.normal(0.0, params.noise_dn, rgb.shape), 0, 255).round().astype(np.uint8)
            yield rgb

    return images(), cams


def transform_pose(cam: Exposure, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of ``cam`` in the frame X' = m[:3, :3] X + m[:3, 3] (m: (4, 4) similarity s R_m | b).

    x_cam is unchanged up to the factor s (same pixels, depth x s): R' = R R_m^T, t' = s t - R' b.
    """
    a, b = np.asarray(m, np.float64)[:3, :3], np.asarray(m, np.float64)[:3, 3]
    s = np.cbrt(np.linalg.det(a))
    r_new = cam.R @ (a / s).T
    return r_new, s * cam.t - r_new @ b


def write_images(
    folder: str | Path,
    images,
    cameras: list[Exposure],
    perturb: np.ndarray | None = None,
    origin=None,
    prefix: str = "",
    jpeg_quality: int = 92,
) -> list[dict]:
    """Write each image (atomically) as ``folder/prefix + camera.image`` and return the cameras.json
    entries, with poses moved into the frame ``perturb`` maps the mesh frame to (identity if None).

    origin is accepted for the caller's convenience and not applied: poses stay relative to the
    frame origin (``X_local = X_world - frame_origin``).
    """
    from PIL import Image

    from storage.atomic import write_bytes_atomic

    folder = Path(folder)
    out = []
    for rgb, cam in zip(images, cameras):
        name = prefix + cam.image
        buf = io.BytesIO()
        fmt = "PNG" if name.lower().endswith(".png") else "JPEG"
        Image.fromarray(rgb).save(buf, format=fmt, **({"quality": jpeg_quality} if fmt == "JPEG" else {}))
        write_bytes_atomic(folder / name, buf.getvalue())
        entry = cam.to_json()
        entry["image"] = name
        if perturb is not None:
            r, t = transform_pose(cam, perturb)
            entry["R"], entry["t"] = r.tolist(), t.tolist()
        out.append(entry)
    return out
