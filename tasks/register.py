"""Register the MLS cloud to the photogrammetric mesh (Liu et al. 2023, section 3.1).

The paper registers the two captures in two steps: SAC-IA (FPFH features + sample consensus,
1000 iterations, 10 cm) for a coarse alignment, then Scale-ICP (1000 iterations, 1 mm) for the
fine similarity. Here:

* **coarse**: both clouds are voxel-downsampled (``cfg.voxel_m``), normals and FPFH descriptors are
  computed, and Open3D's RANSAC on mutual feature matches estimates a rigid transform. The target
  (mesh vertices, which include roofs and everything away from the street) is first cropped to the
  source's bounding box grown by ``CROP_MARGIN_M``. A rotation prior (``ROTATION_PRIOR_DEG``) rejects
  implausible hypotheses before they are scored.
* **fine**: a similarity ICP over a coarse-to-fine schedule of correspondence distances
  (``FINE_DISTANCES_M``). See :func:`fine_register` for what the paper's "1 mm" means here.

Frames: every array is campus-local metres (float64), x east, y north, z up. The returned matrix
maps *source* (MLS) coordinates to *target* (mesh) coordinates: ``target ~= s R source + t``.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from storage.errors import InputError
from tasks.config import RegistrationConfig

_reg = o3d.pipelines.registration

# Parameters not (yet) in RegistrationConfig; candidates for config fields.
MIN_POINTS = 100  # fewer finite points than this cannot be registered
CROP_MARGIN_M = 10.0  # target is cropped to the source bbox grown by this much
ROTATION_PRIOR_DEG = (5.0, 5.0, 15.0)  # max |roll|, |pitch|, |yaw| (axis-angle components) of a hypothesis
NORMAL_RADIUS_VOXELS = 2.5  # normal estimation radius, in voxels
FPFH_RADIUS_VOXELS = 5.0  # FPFH radius, in voxels
SAC_MIN_THRESHOLD_VOXELS = 0.5  # RANSAC inlier distance is at least this many voxels (see coarse_register)
SAC_ATTEMPTS = 3  # independent RANSAC runs (different seeds); the best fitness wins
FINE_DISTANCES_M = (1.0, 0.3, 0.15)  # ICP max correspondence distance schedule
FINE_COARSE_POINTS = 60_000  # source points used in the loose (>= 0.3 m) ICP levels
FINE_LEVEL_ITERATIONS = 30  # iteration cap of every ICP level but the last (which uses cfg.icp_iterations)
PRE_CAP_FACTOR = 8  # random pre-cap (before voxelling) at this many times cfg.max_points


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """The similarity that maps source (MLS) onto target (mesh) coordinates.

    matrix: (4, 4) float64, ``[sR | t; 0 0 0 1]``, campus-local metres.
    scale: s (1.0 when scale is not estimated).
    fitness: share of (subsampled) source points with a target point within the last ICP distance.
    inlier_rmse_m: RMS point-to-plane residual of those points, metres.
    coarse_fitness: the coarse (RANSAC) stage's fitness at its inlier distance.
    n_source, n_target: points actually used (after NaN removal, cropping and subsampling).
    seconds: wall time of the whole registration.
    method: short description of what ran (e.g. "sac-ia+plane-scale-icp", "identity").
    """

    matrix: np.ndarray
    scale: float
    fitness: float
    inlier_rmse_m: float
    coarse_fitness: float
    n_source: int
    n_target: int
    seconds: float
    method: str
    details: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "matrix": self.matrix.tolist(),
            "scale": self.scale,
            "fitness": self.fitness,
            "inlier_rmse_m": self.inlier_rmse_m,
            "coarse_fitness": self.coarse_fitness,
            "n_source": self.n_source,
            "n_target": self.n_target,
            "seconds": self.seconds,
            "method": self.method,
        }


# --------------------------------------------------------------------------- similarity algebra


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


def _rotation_vector(r: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (3,) axis * angle (radians)."""
    cos = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    if angle < 1e-12:
        return np.zeros(3)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return w * angle / (2.0 * np.sin(angle))


def _small_rotation(w: np.ndarray) -> np.ndarray:
    """(3,) rotation vector -> (3, 3) rotation (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


# --------------------------------------------------------------------------- input handling


def _finite_xyz(xyz: np.ndarray, name: str) -> np.ndarray:
    """Validate an (n, 3) array; drop non-finite rows; raise InputError when too few remain."""
    a = np.asarray(xyz)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(None, f"{name} must be an (n, 3) array of metres, got shape {a.shape}")
    a = a.astype(np.float64, copy=False)
    ok = np.isfinite(a).all(axis=1)
    if not ok.all():
        a = a[ok]
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
        a = np.asarray(_cloud(a).voxel_down_sample(voxel_m).points)
    if len(a) > max_points:
        a = a[np.sort(rng.choice(len(a), max_points, replace=False))]
    return a


def crop_to_box(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Boolean (n,) mask of points inside the axis-aligned box [lo, hi] ((3,) metres)."""
    return np.all((xyz >= lo) & (xyz <= hi), axis=1)


def _cloud(xyz: np.ndarray, normals: np.ndarray | None = None) -> o3d.geometry.PointCloud:
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, dtype=np.float64)))
    if normals is not None:
        pc.normals = o3d.utility.Vector3dVector(np.ascontiguousarray(normals, dtype=np.float64))
    return pc


def _estimate_normals(pc: o3d.geometry.PointCloud, radius_m: float, viewpoint: np.ndarray) -> None:
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=30))
    # FPFH histograms change when a normal flips, so both clouds must orient alike: towards one
    # common viewpoint (above the MLS centroid, i.e. over the street), which also makes facade
    # normals point outwards, as a mesh's do.
    pc.orient_normals_towards_camera_location(viewpoint)


# --------------------------------------------------------------------------- coarse: SAC-IA


def _fpfh(pc: o3d.geometry.PointCloud, voxel_m: float):
    return _reg.compute_fpfh_feature(
        pc, o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * voxel_m, max_nn=100)
    )


def coarse_register(
    source_xyz: np.ndarray, target_xyz: np.ndarray, cfg: RegistrationConfig
) -> tuple[np.ndarray, float, float]:
    """SAC-IA: FPFH features + RANSAC on mutual feature matches -> rigid (4, 4) source -> target.

    source_xyz, target_xyz: (n, 3) / (m, 3) float64 campus-local metres, already thinned and the
    target cropped around the source. Both are voxel-downsampled at ``cfg.voxel_m``; normals use a
    radius of ``NORMAL_RADIUS_VOXELS`` voxels and FPFH ``FPFH_RADIUS_VOXELS`` voxels.

    The paper's 10 cm (``cfg.sac_threshold_m``) is the RANSAC inlier distance, but two independent
    voxel grids put their centroids up to ~half a voxel apart on the same surface, so a 10 cm
    threshold on 0.3 m voxels counts only a fraction of the true inliers and makes the consensus
    noisy. The inlier distance used is ``max(cfg.sac_threshold_m, SAC_MIN_THRESHOLD_VOXELS *
    cfg.voxel_m)``; the fine stage does the rest. Each of ``SAC_ATTEMPTS`` runs does
    ``cfg.sac_iterations`` RANSAC iterations (seeded ``cfg.seed + attempt``); hypotheses whose
    rotation exceeds ``ROTATION_PRIOR_DEG`` or whose sampled edges disagree in length by > 10 %
    are rejected before scoring; the best-scoring run wins.

    Returns (matrix, fitness, inlier_distance_m).
    """
    voxel = float(cfg.voxel_m)
    viewpoint = source_xyz.mean(axis=0) + np.array([0.0, 0.0, 5.0])
    src = _cloud(source_xyz).voxel_down_sample(voxel)
    tgt = _cloud(target_xyz).voxel_down_sample(voxel)
    if len(src.points) < MIN_POINTS or len(tgt.points) < MIN_POINTS:
        raise InputError(
            None,
            f"after {voxel} m voxels only {len(src.points)} source / {len(tgt.points)} target points remain "
            f"(need {MIN_POINTS}); the clouds are too small or do not overlap",
        )
    for pc in (src, tgt):
        _estimate_normals(pc, NORMAL_RADIUS_VOXELS * voxel, viewpoint)
    f_src, f_tgt = _fpfh(src, voxel), _fpfh(tgt, voxel)
    distance = max(float(cfg.sac_threshold_m), SAC_MIN_THRESHOLD_VOXELS * voxel)
    checkers = [
        _reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        _reg.CorrespondenceCheckerBasedOnDistance(distance),
        _reg.CorrespondenceCheckerBasedOnSourceRotation(np.radians(ROTATION_PRIOR_DEG).reshape(3, 1)),
    ]
    best = None
    for attempt in range(SAC_ATTEMPTS):
        o3d.utility.random.seed(int(cfg.seed) + attempt)
        res = _reg.registration_ransac_based_on_feature_matching(
            src, tgt, f_src, f_tgt, True, distance,
            _reg.TransformationEstimationPointToPoint(False), 3, checkers,
            _reg.RANSACConvergenceCriteria(int(cfg.sac_iterations), 0.9999),
        )
        if best is None or (res.fitness, -res.inlier_rmse) > (best.fitness, -best.inlier_rmse):
            best = res
    return np.asarray(best.transformation).copy(), float(best.fitness), distance
