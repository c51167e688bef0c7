"""Cameras: one in-memory model (OpenCV pinhole + radial-tangential distortion) and readers/writers of the
camera files users have.

Formats (chosen by name, see :func:`storage.formats.camera_files.read_cameras`):

- ``cameras.json`` (ms3d's own, written by ``synth``): ``{"frame": "MLS" | "mesh", "frame_origin": [x, y, z],
  "cameras": [{"image", "K", "R", "t", "width", "height", "dist"?}]}``;
- COLMAP text model: a sparse folder holding ``cameras.txt`` + ``images.txt`` (or either file);
- ContextCapture / iTwin Capture BlocksExchange XML (``*.xml``); code in :mod:`storage.formats.camera_files`.

Conventions (OpenCV): ``x_c = R X + t`` (R world-to-camera, t = -R C), x right, y down, z forward; normalised
``(x, y) = (x_c / z_c, y_c / z_c)`` is distorted by ``dist = (k1, k2, p1, p2, k3)``::

    r² = x² + y²,  g = 1 + k1 r² + k2 r⁴ + k3 r⁶
    x_d = x g + 2 p1 x y + p2 (r² + 2 x²),  y_d = y g + p1 (r² + 2 y²) + 2 p2 x y
    (u, v) = K[:2, :2] (x_d, y_d) + K[:2, 2]

with integer (u, v) at pixel centres (the top-left pixel's centre is (0, 0)). COLMAP puts (0.5, 0.5) there:
its readers and writers shift the principal point by half a pixel.

Frames: ``CameraSet.frame`` says which input the poses belong to ("mesh": the mesh's world coordinates,
which are the campus frame once the origin is subtracted; "MLS": the point clouds' world coordinates, moved
by the registration) and ``frame_origin`` (3,) float64 the world position of the file's zero. cameras.json
states both; COLMAP and BlocksExchange files are taken as world coordinates in the campus CRS from the
photogrammetry that made the mesh: frame "mesh", frame_origin (0, 0, 0).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.errors import InputError


def distort(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """(n, 2) float64 normalised image coordinates -> (n, 2) distorted ones (OpenCV k1, k2, p1, p2, k3).

    >>> distort(np.array([[0.5, 0.0]]), np.array([0.1, 0.0, 0.0, 0.0, 0.0])).round(6).tolist()
    [[0.5125, 0.0]]
    """
    k1, k2, p1, p2, k3 = np.asarray(dist, np.float64)
    x, y = xy[:, 0], xy[:, 1]
    r2 = x * x + y * y
    g = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * g + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x)
    yd = y * g + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y
    return np.stack([xd, yd], axis=1)


def project_points(xyz: np.ndarray, K: np.ndarray, R: np.ndarray, t: np.ndarray,
                   dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """xyz (n, 3) metres (the camera's frame) -> ((n, 2) float64 pixel (u, v), (n,) float64 depth along the
    optical axis). Depth <= 0: behind the camera, uv meaningless (NaN/inf at depth 0). With distortion, uv is
    NaN beyond the radius where the radial model folds back (d(r g(r))/dr <= 0): such points lie far outside
    the lens's field and would otherwise land inside the image."""
    xc = np.asarray(xyz, np.float64).reshape(-1, 3) @ np.asarray(R, np.float64).T + np.asarray(t, np.float64)
    z = xc[:, 2]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        xy = xc[:, :2] / z[:, None]
        if dist is not None and np.any(np.asarray(dist) != 0):
            k1, k2, _, _, k3 = np.asarray(dist, np.float64)
            r2 = (xy * xy).sum(axis=1)
            folded = ~(1.0 + r2 * (3.0 * k1 + r2 * (5.0 * k2 + r2 * 7.0 * k3)) > 0)
            xy = distort(xy, dist)
            xy[folded] = np.nan
        uv = xy @ np.asarray(K, np.float64)[:2, :2].T + np.asarray(K, np.float64)[:2, 2]
    return uv, z


@dataclass(frozen=True)
class Camera:
    """One image. image: path as the file names it; K: (3, 3) float64 pixels; dist: (5,) float64 (k1, k2,
    p1, p2, k3); R: (3, 3) float64 world-to-camera; t: (3,) float64 metres; width, height: pixels."""

    image: str
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int
    dist: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @property
    def centre(self) -> np.ndarray:
        """(3,) float64 camera centre C = -R^T t."""
        return -self.R.T @ self.t

    def project(self, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) float64 -> ((n, 2) pixel (u, v) with distortion, (n,) depth); see :func:`project_points`."""
        return project_points(xyz, self.K, self.R, self.t, self.dist)


@dataclass(frozen=True)
class CameraSet:
    """The cameras of one file. frame: "mesh" or "MLS"; frame_origin: (3,) float64 world metres of the
    file's zero (X_world = X_file + frame_origin); fmt: "cameras.json", "colmap" or "blocksexchange";
    skipped: entries without a usable pose (not in ``cameras``); crs: the file's stated CRS, if any."""

    cameras: list[Camera]
    frame: str = "mesh"
    frame_origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fmt: str = "cameras.json"
    skipped: int = 0
    crs: str | None = None


def check_pose(path: Path, name: str, K, R, t, width, height, dist) -> Camera:
    """A Camera from parsed values, or InputError naming ``path`` and the image when a number is not
    finite, R is not a rotation or the size is not positive."""
    K, R, t = (np.asarray(a, np.float64) for a in (K, R, t))
    dist = np.zeros(5) if dist is None else np.asarray(dist, np.float64)
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,) or dist.shape != (5,):
        raise InputError(path, f"camera {name!r}: K and R must be 3x3, t 3 numbers, dist 5 numbers")
    if not all(np.isfinite(a).all() for a in (K, R, t, dist)):
        raise InputError(path, f"camera {name!r}: a pose or intrinsic value is not a finite number")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
        raise InputError(path, f"camera {name!r}: R is not a rotation (R R^T != I or det < 0)")
    if int(width) <= 0 or int(height) <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise InputError(path, f"camera {name!r}: image size and focal length must be positive")
    return Camera(str(name), K, R, t, int(width), int(height), dist)


# ------------------------------------------------------------------------------------- cameras.json

def read_cameras_json(path: Path) -> CameraSet:
    """ms3d's cameras.json (module docstring); ``dist`` is optional (default no distortion)."""
    try:
        doc = json.loads(Path(path).read_text())
        entries = doc["cameras"]
        fo = tuple(float(v) for v in doc.get("frame_origin", [0.0, 0.0, 0.0]))
        frame = str(doc.get("frame", "MLS"))
        cams = [check_pose(path, e["image"], e["K"], e["R"], e["t"], e["width"], e["height"], e.get("dist"))
                for e in entries]
    except InputError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise InputError(path, f"not a cameras.json ({type(e).__name__}: {e})") from None
    if frame.lower() not in ("mls", "mesh") or len(fo) != 3:
        raise InputError(path, f"'frame' must be 'MLS' or 'mesh' and 'frame_origin' 3 numbers (got {frame!r})")
    return CameraSet(cams, "MLS" if frame.lower() == "mls" else "mesh", fo, "cameras.json")


def write_cameras_json(path: Path, cams: CameraSet) -> None:
    """Write ``cams`` as a cameras.json (with ``dist``)."""
    entries = [{"image": c.image, "K": c.K.tolist(), "R": c.R.tolist(), "t": c.t.tolist(), "width": c.width,
                "height": c.height, "dist": np.asarray(c.dist, np.float64).tolist()} for c in cams.cameras]
    Path(path).write_text(json.dumps({"frame": cams.frame, "frame_origin": list(cams.frame_origin),
                                      "cameras": entries}, indent=1))
