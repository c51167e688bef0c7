"""Register the MLS cloud to the photogrammetric mesh (Liu et al. 2023, section 3.1).

The paper registers the two captures in two steps: SAC-IA (FPFH features + sample consensus,
1000 iterations, 10 cm) for a coarse alignment, then Scale-ICP (1000 iterations, 1 mm) for the
fine similarity. Here:

* **coarse** (:func:`coarse_register`): the target (mesh vertices, which include roofs and
  everything away from the street) is cropped to the source's bounding box grown by
  ``CROP_MARGIN_M``; both clouds are voxel-downsampled (``cfg.voxel_m``), FPFH descriptors are
  computed at curved keypoints and matched within a spatial gate, and Open3D's RANSAC on those
  matches estimates a rigid transform. A rotation prior (``ROTATION_PRIOR_DEG``) rejects
  implausible hypotheses before they are scored.
* **fine** (:func:`fine_register`): a point-to-plane similarity ICP against denoised local planes
  of the mesh (:func:`surface_planes`), Tukey-weighted, over a coarse-to-fine schedule of
  correspondence distances (``FINE_DISTANCES_M``). Open3D's point-to-point ICP with scaling (the
  literal Scale-ICP) is kept as ``FINE_METHOD = "point"``; it is slower and, against noisy or
  defective mesh vertices, less accurate (figures in fine_register).
  The paper's "1 mm" is the convergence threshold (see :func:`fine_register`).

Layout: the coarse stage is in :mod:`tasks.register_coarse`, the fine stage in :mod:`tasks.register_fine`,
the similarity algebra in :mod:`tasks.register_base`; this module holds the public entry points
(:func:`register_clouds`, :func:`check_coregistered`) and re-exports what callers import.

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
from tasks.register_base import (
    MIN_POINTS,
    StepClock,
    apply_similarity,
    compare_transforms,
    compose_similarity,
    decompose_similarity,
    o3d_cloud,
)
from tasks.register_coarse import coarse_register, consistent_matches, match_features
from tasks.register_fine import (
    FINE_DISTANCES_M,
    FINE_METHOD,
    fine_register,
    plane_similarity_icp,
    point_similarity_icp,
    surface_planes,
)

# Parameters not (yet) in RegistrationConfig; candidates for config fields.
CROP_MARGIN_M = 10.0  # target is cropped to the source bbox grown by this much
FINE_CROP_M = 3.0  # fine stage keeps mesh vertices this near the coarsely aligned source
TARGET_MAX_POINTS = 3_000_000  # random cap on cropped mesh vertices
CHECK_POINTS = 50_000  # source points sampled by check_coregistered
CHECK_VOXEL_M = 0.2  # ... after thinning at this voxel size
CHECK_MIN_GROUP_SHARE = 0.05  # an orientation group counts in check_coregistered from this share of points
LOW_FITNESS = 0.5  # register_clouds warns when fewer source points than this find the mesh
PRE_CAP_FACTOR = 8  # random pre-cap (before voxelling) at this many times cfg.max_points


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """The similarity that maps source (MLS) onto target (mesh) coordinates.

    matrix: (4, 4) float64, ``[sR | t; 0 0 0 1]``, campus-local metres.
    scale: s (1.0 when scale is not estimated).
    fitness: share of (subsampled) source points with a target point within the last ICP distance.
    inlier_rmse_m: RMS point-to-plane residual of those points, metres.
    coarse_fitness: the coarse (RANSAC) stage's fitness at its inlier distance.
    n_source: MLS points used (after NaN removal, voxelling and the cap).
    n_target: local mesh planes the fine stage used (``surface_planes`` of the cropped vertices;
    raw cropped vertices with ``FINE_METHOD = "point"``).
    details: coarse matrix, keypoint / match counts and (wall, CPU) seconds per step.
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


# --------------------------------------------------------------------------- input handling


def _check_shape(xyz: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(xyz)
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(None, f"{name} must be an (n, 3) array of metres, got shape {a.shape}")
    return a


def _finite_xyz(
    xyz: np.ndarray, name: str, cap: int | None = None, rng: np.random.Generator | None = None
) -> np.ndarray:
    """(n, 3) any float dtype -> (k, 3) float64 finite rows; raise InputError when < MIN_POINTS remain.

    With ``cap``, at most ``cap`` random rows (drawn with ``rng``) are kept *before* the float64
    copy, so a huge float32 input is never duplicated whole.
    """
    a = _check_shape(xyz, name)
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


def _target_near(
    target_xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray, normals: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Finite mesh vertices inside [lo, hi] (and their normals) as float64; InputError if < MIN_POINTS.

    Cropping happens on the caller's dtype, so only the kept vertices are copied.
    """
    raw = _check_shape(target_xyz, "mesh vertices")
    if normals is not None and np.shape(normals) != raw.shape:
        raise InputError(None, f"target_normals has shape {np.shape(normals)}, mesh vertices {raw.shape}")
    finite = np.isfinite(raw).all(axis=1)
    if finite.sum() < MIN_POINTS:
        raise InputError(
            None,
            f"mesh vertices have {int(finite.sum())} finite points (of {len(raw)}; the rest NaN/inf); "
            f"registration needs at least {MIN_POINTS}",
        )
    keep = np.flatnonzero(finite & crop_to_box(raw, lo, hi))
    if len(keep) < MIN_POINTS:
        raise InputError(
            None,
            f"only {len(keep)} mesh vertices lie within {CROP_MARGIN_M} m of the MLS cloud's extent "
            f"{np.round(lo, 1).tolist()} - {np.round(hi, 1).tolist()}: the inputs do not overlap "
            "(wrong CRS, origin or units?)",
        )
    nrm = None if normals is None else np.asarray(normals)[keep].astype(np.float64)
    return raw[keep].astype(np.float64), nrm


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


# --------------------------------------------------------------------------- public entry points


def _near(points: np.ndarray, reference: np.ndarray, distance_m: float) -> np.ndarray:
    """Boolean (n,) mask keeping every point within ``distance_m`` of a ``reference`` point.

    A voxel-hash test (cells of ``distance_m``, dilated by one cell), so it also keeps some points
    up to ~2 sqrt(3) ``distance_m`` away. points: (n, 3), reference: (k, 3) float64 metres.
    """
    lo = np.minimum(points.min(axis=0), reference.min(axis=0))
    cells_p = np.floor((points - lo) / distance_m).astype(np.int64) + 1
    cells_r = np.floor((reference - lo) / distance_m).astype(np.int64) + 1
    dims = np.maximum(cells_p.max(axis=0), cells_r.max(axis=0)) + 2
    ref = np.unique(np.ravel_multi_index(cells_r.T, dims))
    offsets = np.stack(np.meshgrid(*([np.arange(-1, 2)] * 3), indexing="ij"), axis=-1).reshape(-1, 3)
    ref_cells = np.stack(np.unravel_index(ref, dims), axis=1)
    dilated = np.unique(np.ravel_multi_index((ref_cells[:, None, :] + offsets[None]).reshape(-1, 3).T, dims))
    return np.isin(np.ravel_multi_index(cells_p.T, dims), dilated)


def _orientation_groups(xyz: np.ndarray) -> np.ndarray:
    """(n,) int group of each point's surface: 0 horizontal, 1..6 vertical by normal azimuth (30 deg bins)."""
    pc = o3d_cloud(xyz)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    n = np.asarray(pc.normals)
    azimuth = np.degrees(np.arctan2(n[:, 1], n[:, 0])) % 180.0
    return np.where(np.abs(n[:, 2]) > 0.7, 0, 1 + np.minimum((azimuth // 30).astype(np.int64), 5))


def check_coregistered(
    source_xyz: np.ndarray, target_xyz: np.ndarray, tol_m: float = 0.2, seed: int = 0
) -> tuple[bool, float]:
    """Do two clouds already overlap? (Used when registration is switched off.)

    source_xyz: (n, 3) MLS points, target_xyz: (m, 3) mesh vertices, float64 campus-local metres.
    Thins the source (``CHECK_VOXEL_M`` voxels, at most ``CHECK_POINTS``) and measures each point's
    distance to the nearest target point. A plain median would hide a shift along the dominant
    surfaces (across a street, the ground and the side walls do not move away from the mesh, and
    they can be most of the points), so points are grouped by surface orientation (horizontal;
    vertical in six 30 degree azimuth bins) and the largest median over the groups holding at least
    ``CHECK_MIN_GROUP_SHARE`` of the points is used. Returns (that median <= tol_m, that median in
    metres). A shift parallel to every well-populated surface family stays invisible.
    """
    rng = np.random.default_rng(seed)
    src = _finite_xyz(source_xyz, "MLS point cloud", PRE_CAP_FACTOR * CHECK_POINTS, rng)
    src = subsample_for_registration(src, CHECK_POINTS, CHECK_VOXEL_M, rng)
    lo, hi = src.min(axis=0) - CROP_MARGIN_M, src.max(axis=0) + CROP_MARGIN_M
    try:
        tgt, _ = _target_near(target_xyz, lo, hi)
    except InputError:
        return False, float("inf")
    dist, _ = cKDTree(tgt).query(src, workers=-1)
    groups = _orientation_groups(src)
    counts = np.bincount(groups, minlength=7)
    medians = [
        np.median(dist[groups == g]) for g in range(7) if counts[g] >= CHECK_MIN_GROUP_SHARE * len(src)
    ]
    worst = float(max(medians)) if medians else float(np.median(dist))
    return worst <= tol_m, worst


def register_clouds(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    cfg: RegistrationConfig,
    target_normals: np.ndarray | None = None,
) -> RegistrationResult:
    """Estimate the similarity mapping the MLS cloud onto the mesh: SAC-IA, then Scale-ICP.

    source_xyz: (n, 3) MLS points; target_xyz: (m, 3) mesh vertices; target_normals: optional
    (m, 3) vertex normals (estimated when None). float64 campus-local metres; NaN/inf rows are
    dropped. Either input may be millions of points: the source is voxelled at
    ``cfg.fine_voxel_m`` and capped at ``cfg.max_points``; the target is cropped to the source's
    bounding box grown by ``CROP_MARGIN_M``, then, for the fine stage, to within ``FINE_CROP_M``
    of the coarsely aligned source.

    With ``cfg.enabled`` False nothing is estimated: the identity is returned after
    :func:`check_coregistered`, which warns when the clouds do not look co-registered.

    Raises InputError when an input has fewer than ``MIN_POINTS`` finite points or the clouds do
    not overlap; warns when the final fitness is below ``LOW_FITNESS``. Deterministic for a given
    ``cfg.seed`` (and Open3D thread count). ``details`` of the result holds the coarse matrix,
    keypoint / match counts and the (wall, CPU) seconds of each step.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    clock = StepClock(t0)
    src = _finite_xyz(source_xyz, "MLS point cloud", PRE_CAP_FACTOR * cfg.max_points, rng)
    if not cfg.enabled:
        ok, median = check_coregistered(src, target_xyz, seed=cfg.seed)
        if not ok:
            warnings.warn(
                f"registration is disabled but the MLS cloud lies a median {median:.2f} m from the mesh: "
                "are the inputs really co-registered?",
                stacklevel=2,
            )
        return RegistrationResult(
            np.eye(4),
            1.0,
            float("nan"),
            float("nan"),
            float("nan"),
            len(src),
            len(target_xyz),
            time.perf_counter() - t0,
            "identity (registration disabled)",
            {"median_distance_m": median},
        )
    src = subsample_for_registration(src, cfg.max_points, cfg.fine_voxel_m, rng)
    lo, hi = src.min(axis=0) - CROP_MARGIN_M, src.max(axis=0) + CROP_MARGIN_M
    tgt, nrm = _target_near(target_xyz, lo, hi, target_normals)
    if len(tgt) > TARGET_MAX_POINTS:
        pick = np.sort(rng.choice(len(tgt), TARGET_MAX_POINTS, replace=False))
        tgt, nrm = tgt[pick], (None if nrm is None else nrm[pick])
    clock.lap("thin+crop")
    coarse, coarse_fit, coarse_info = coarse_register(src, tgt, cfg)
    clock.lap("coarse")

    near = _near(tgt, apply_similarity(coarse, src), FINE_CROP_M)
    tgt_f = tgt[near]
    if len(tgt_f) < MIN_POINTS:
        raise InputError(None, "the coarse registration left no mesh vertices near the MLS cloud")
    if FINE_METHOD == "plane":
        tgt_f, nrm_f = surface_planes(tgt_f, None if nrm is None else nrm[near])
    else:
        nrm_f = None
    clock.lap("fine-prep")
    matrix, fit, rmse, method = fine_register(src, tgt_f, nrm_f, coarse, cfg, rng)
    clock.lap("fine")
    if fit < LOW_FITNESS:
        warnings.warn(
            f"only {100 * fit:.0f} % of the MLS points lie within {FINE_DISTANCES_M[-1]} m of the mesh after "
            "registration: check the result (do the inputs overlap? is the mesh badly degraded?)",
            stacklevel=2,
        )
    scale = decompose_similarity(matrix)[0]
    return RegistrationResult(
        matrix,
        float(scale),
        fit,
        rmse,
        coarse_fit,
        len(src),
        len(tgt_f),
        time.perf_counter() - t0,
        f"sac-ia+{method}",
        {"coarse_matrix": coarse, "coarse": coarse_info, "seconds": clock.laps},
    )


__all__ = [
    "MIN_POINTS",
    "RegistrationResult",
    "apply_similarity",
    "check_coregistered",
    "coarse_register",
    "compare_transforms",
    "compose_similarity",
    "consistent_matches",
    "crop_to_box",
    "decompose_similarity",
    "fine_register",
    "match_features",
    "plane_similarity_icp",
    "point_similarity_icp",
    "register_clouds",
    "subsample_for_registration",
    "surface_planes",
]
