"""What the registration modules share: the similarity algebra (``target ~= s R source + t``), the
Open3D cloud wrapper, the per-step clock, and the checking and thinning of input clouds.

Frames: every array is campus-local metres (float64), x east, y north, z up. A similarity is a (4, 4)
float64 matrix ``[sR | t; 0 0 0 1]`` mapping *source* (MLS) to *target* (mesh) coordinates.
"""

from __future__ import annotations

import time

import numpy as np
import open3d as o3d

from storage.errors import InputError

MIN_POINTS = 100  # fewer finite points than this cannot be registered
SANE_SCALE = (0.5, 2.0)  # a fitted scale outside this is a collapsed fit, not a measurement


class FitFailed(InputError):
    """The fit itself failed (ICP lost the overlap, the similarity collapsed), although the inputs are
    readable and overlap: the registration guard keeps the transform in place and warns, instead of
    ending the run (unless ``registration.strict``)."""
PRE_CAP_FACTOR = 8  # random pre-cap (before voxelling) at this many times the final cap


def apply_similarity(matrix: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    """matrix: (4, 4); xyz: (n, 3) -> (n, 3) float64, ``s R xyz + t``."""
    m = np.asarray(matrix, dtype=np.float64)
    return np.asarray(xyz, dtype=np.float64) @ m[:3, :3].T + m[:3, 3]


def decompose_similarity(matrix: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """matrix: (4, 4) similarity -> (scale, R (3, 3) proper rotation, t (3,)).

    The scale is the cube root of det(sR); R is the nearest rotation (SVD) to ``sR / s``.
    """
    m = np.asarray(matrix, dtype=np.float64)
    a = m[:3, :3]
    det = np.linalg.det(a)
    if not det > 0:
        raise ValueError(f"not a proper similarity (det of the 3x3 block is {det:g})")
    s = float(np.cbrt(det))
    u, _, vt = np.linalg.svd(a / s)
    r = u @ vt
    return s, r, m[:3, 3].copy()


def compose_similarity(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """(s, R (3, 3), t (3,)) -> (4, 4) float64."""
    m = np.eye(4)
    m[:3, :3] = scale * np.asarray(rotation, dtype=np.float64)
    m[:3, 3] = translation
    return m


def compare_transforms(estimated: np.ndarray, truth: np.ndarray, at: np.ndarray | None = None) -> dict:
    """Errors of an estimated similarity against a known one (both (4, 4), source -> target).

    rotation_error_deg: angle of ``R_est R_true^T``.
    translation_error_m: ``|M_est(c) - M_true(c)|`` for a point c = ``at`` ((3,) metres, source frame;
    default the origin). Pass the source data centroid: a translation compared at the frame origin
    mixes in rotation error times the distance to the origin, which says nothing about the data.
    scale_error_pct: ``100 (s_est / s_true - 1)``.
    """
    s_e, r_e, _ = decompose_similarity(estimated)
    s_t, r_t, _ = decompose_similarity(truth)
    cos = (np.trace(r_e @ r_t.T) - 1.0) / 2.0
    c = np.zeros((1, 3)) if at is None else np.asarray(at, dtype=np.float64).reshape(1, 3)
    d = apply_similarity(estimated, c) - apply_similarity(truth, c)
    return {
        "rotation_error_deg": float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))),
        "translation_error_m": float(np.linalg.norm(d)),
        "scale_error_pct": float(100.0 * (s_e / s_t - 1.0)),
    }


def small_rotation(w: np.ndarray) -> np.ndarray:
    """(3,) rotation vector -> (3, 3) rotation (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


class StepClock:
    """Wall and CPU seconds per named step (reported in RegistrationResult.details)."""

    def __init__(self, t0: float):
        self.t, self.c, self.laps = t0, time.process_time(), {}

    def lap(self, name: str) -> None:
        now, cpu = time.perf_counter(), time.process_time()
        self.laps[name] = (round(now - self.t, 2), round(cpu - self.c, 2))
        self.t, self.c = now, cpu


def o3d_cloud(xyz: np.ndarray) -> o3d.geometry.PointCloud:
    """(n, 3) metres -> an Open3D point cloud (float64 copy only when needed)."""
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, dtype=np.float64)))


# --------------------------------------------------------------------------- input handling


def check_xyz_shape(xyz: np.ndarray, name: str) -> np.ndarray:
    """``xyz`` as an array; InputError naming it unless it is (n, 3)."""
    a = np.asarray(xyz)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(None, f"{name} must be an (n, 3) array of metres, got shape {a.shape}")
    return a


def finite_xyz(
    xyz: np.ndarray, name: str, cap: int | None = None, rng: np.random.Generator | None = None
) -> np.ndarray:
    """(n, 3) any float dtype -> (k, 3) float64 finite rows; raise InputError when < MIN_POINTS remain.

    With ``cap``, at most ``cap`` random rows (drawn with ``rng``) are kept *before* the float64
    copy, so a huge float32 input is never duplicated whole.
    """
    a = check_xyz_shape(xyz, name)
    if cap is not None and len(a) > cap:
        a = a[np.sort(rng.choice(len(a), cap, replace=False))]
    ok = np.isfinite(a).all(axis=1)
    a = (a if ok.all() else a[ok]).astype(np.float64, copy=False)
    if len(a) < MIN_POINTS:
        raise InputError(
            None,
            f"{name} has {len(a)} finite points ({int((~ok).sum())} NaN/inf rows dropped); "
            f"registration needs at least {MIN_POINTS}",
        )
    return a


def subsample_for_registration(
    xyz: np.ndarray, max_points: int, voxel_m: float, rng: np.random.Generator
) -> np.ndarray:
    """Thin a cloud for registration: one point (the centroid) per voxel, then at most ``max_points``.

    xyz: (n, 3) float64 metres, finite. voxel_m: voxel edge (<= 0 skips voxelling).
    rng: draws the random pre-cap (at ``PRE_CAP_FACTOR * max_points``, bounding memory for huge
    inputs) and the final cap. Returns (k, 3) float64, k <= max_points. Deterministic for a given rng.
    """
    a = np.asarray(xyz, dtype=np.float64)
    pre_cap = PRE_CAP_FACTOR * max_points
    if len(a) > pre_cap:
        a = a[np.sort(rng.choice(len(a), pre_cap, replace=False))]
    if voxel_m > 0 and len(a):
        a = np.asarray(o3d_cloud(a).voxel_down_sample(voxel_m).points)
    if len(a) > max_points:
        a = a[np.sort(rng.choice(len(a), max_points, replace=False))]
    return a


def crop_to_box(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Boolean (n,) mask of points inside the axis-aligned box [lo, hi] ((3,) metres)."""
    return np.all((xyz >= lo) & (xyz <= hi), axis=1)


__all__ = [
    "MIN_POINTS",
    "PRE_CAP_FACTOR",
    "StepClock",
    "apply_similarity",
    "check_xyz_shape",
    "compare_transforms",
    "compose_similarity",
    "crop_to_box",
    "decompose_similarity",
    "finite_xyz",
    "o3d_cloud",
    "small_rotation",
    "subsample_for_registration",
]
