"""Register the MLS cloud to the photogrammetric mesh (Liu et al. 2023, section 3.1).

The paper registers the two captures in two steps: SAC-IA (FPFH features + sample consensus,
1000 iterations, 10 cm) for a coarse alignment, then Scale-ICP (1000 iterations, 1 mm) for the
fine similarity. Here:

* **target** (:func:`mesh_registration_target`): area-weighted samples of the mesh *surface* (faces
  within ``CROP_MARGIN_M`` of the source's bounding box), about ``TARGET_SPACING_M`` apart, with
  their face normals; so the target does not depend on the tessellation (a coarse LoD2-like model
  with a few hundred large triangles works as well as a dense photogrammetric mesh).
* **coarse** (:func:`coarse_register`): both clouds are voxel-downsampled (``cfg.voxel_m``), FPFH
  descriptors are computed at curved keypoints and matched within a spatial gate, and Open3D's RANSAC on those
  matches estimates a rigid transform. A rotation prior (``ROTATION_PRIOR_DEG``) rejects
  implausible hypotheses before they are scored.
* **fine** (:func:`fine_register`): a point-to-plane similarity ICP against denoised local planes
  of the mesh (:func:`surface_planes`), Tukey-weighted, over a coarse-to-fine schedule of
  correspondence distances (``FINE_DISTANCES_M``). Open3D's point-to-point ICP with scaling (the
  literal Scale-ICP) is kept as ``FINE_METHOD = "point"``; it is slower and, against noisy or
  defective mesh vertices, less accurate (figures in fine_register).
  The paper's "1 mm" is the convergence threshold (see :func:`fine_register`).

Layout: the coarse stage is in :mod:`tasks.register.coarse`, the fine stage in :mod:`tasks.register.fine`,
the similarity algebra in :mod:`tasks.register.base`; this module holds the public entry points
(:func:`register_clouds`) and re-exports what callers import; the surface target is built in
:mod:`tasks.register.target`, the co-registration and overlap checks are in :mod:`tasks.register.check`.

Frames: every array is campus-local metres (float64), x east, y north, z up. The returned matrix
maps *source* (MLS) coordinates to *target* (mesh) coordinates: ``target ~= s R source + t``.
"""

from __future__ import annotations

import logging
import time
import warnings
from dataclasses import dataclass, field

import numpy as np

from storage.errors import InputError
from tasks.config import RegistrationConfig
from tasks.register import fine as register_fine
from tasks.register.base import (
    MIN_POINTS,
    PRE_CAP_FACTOR,
    SANE_SCALE,
    FitFailed,
    StepClock,
    apply_similarity,
    compare_transforms,
    compose_similarity,
    crop_to_box,
    decompose_similarity,
    finite_xyz,
    subsample_for_registration,
)
from tasks.register.check import (
    CoregistrationCheck,
    check_coregistered,
    check_coregistered_samples,
    check_overlap,
)
from tasks.register.coarse import coarse_register, consistent_matches, match_features
from tasks.register.fine import (
    FINE_DISTANCES_M,
    fine_register,
    plane_similarity_icp,
    point_similarity_icp,
    surface_planes,
)
from tasks.register.target import (
    TARGET_MAX_POINTS,
    TARGET_SPACING_M,
    faces_in_box,
    mesh_arrays,
    mesh_registration_target,
    used_bounds,
)

log = logging.getLogger("ms3d.register")

# Parameters not (yet) in RegistrationConfig; candidates for config fields.
CROP_MARGIN_M = 10.0  # the target samples the faces within this much of the source's bounding box
FINE_CROP_M = 3.0  # fine stage keeps the target samples this near the coarsely aligned source
LOW_FITNESS = 0.5  # register_clouds logs when fewer source points than this find the mesh


@dataclass(frozen=True, eq=False)
class RegistrationResult:
    """The similarity that maps source (MLS) onto target (mesh) coordinates.

    matrix: (4, 4) float64, ``[sR | t; 0 0 0 1]``, campus-local metres.
    scale: s (1.0 when scale is not estimated).
    fitness: share of (subsampled) source points with a target point within the last ICP distance.
    inlier_rmse_m: RMS point-to-plane residual of those points, metres.
    coarse_fitness: the coarse (RANSAC) stage's fitness at its inlier distance.
    n_source: MLS points used (after NaN removal, voxelling and the cap).
    n_target: local planes of the mesh surface the fine stage used (``surface_planes`` of the surface
    samples near the source; the raw samples with ``FINE_METHOD = "point"``); with registration
    disabled, the number of mesh faces.
    details: coarse matrix, keypoint / match counts and (wall, CPU) seconds per step; with
    registration disabled, ``"check"``: the :class:`CoregistrationCheck` as JSON.
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
            "step_seconds": {k: [float(x) for x in v] if isinstance(v, (list, tuple)) else v
                             for k, v in (self.details.get("seconds") or {}).items()},
        }


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


def register_clouds(
    source_xyz: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    cfg: RegistrationConfig,
    target_spacing_m: float = TARGET_SPACING_M,
) -> RegistrationResult:
    """Estimate the similarity mapping the MLS cloud onto the mesh surface: SAC-IA, then Scale-ICP.

    source_xyz: (n, 3) MLS points; vertices: (m, 3) mesh vertices; faces: (k, 3) int64; float64
    campus-local metres. NaN/inf source rows and faces on NaN/inf vertices are dropped. The source
    may be millions of points: it is voxelled at ``cfg.fine_voxel_m`` and capped at
    ``cfg.max_points``. The target is the mesh surface near the source: the faces within
    ``CROP_MARGIN_M`` of its bounding box, sampled about ``target_spacing_m`` apart (at most
    ``TARGET_MAX_POINTS`` samples, :func:`mesh_registration_target`); the fine stage keeps the samples
    within ``FINE_CROP_M`` of the coarsely aligned source.

    With ``cfg.enabled`` False nothing is estimated: the identity is returned after
    :func:`check_coregistered`, which warns when the inputs do not look co-registered (the check is
    in ``details["check"]``).

    Raises InputError when an input is unusable (fewer than ``MIN_POINTS`` finite points, bad faces)
    or the inputs do not overlap; logs (info) when the final fitness is below ``LOW_FITNESS``.
    Deterministic for a given ``cfg.seed`` (and Open3D thread count). ``details`` of the result holds
    the coarse matrix, keypoint / match counts and the (wall, CPU) seconds of each step.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    clock = StepClock(t0)
    v, f = mesh_arrays(vertices, faces)
    src = finite_xyz(source_xyz, "MLS point cloud", PRE_CAP_FACTOR * cfg.max_points, rng)
    if not cfg.enabled:
        check = check_coregistered(src, v, f, seed=cfg.seed)
        if not check.ok:
            warnings.warn(
                f"registration is disabled but {check}: are the inputs really co-registered?", stacklevel=2
            )
        nan = float("nan")
        return RegistrationResult(
            np.eye(4), 1.0, nan, nan, nan, len(src), len(f), time.perf_counter() - t0,
            "identity (registration disabled)", {"check": check.to_json()},
        )  # fmt: skip
    src = subsample_for_registration(src, cfg.max_points, cfg.fine_voxel_m, rng)
    src_lo, src_hi = src.min(axis=0), src.max(axis=0)
    check_overlap(src_lo, src_hi, *used_bounds(v, f), "the MLS point cloud (campus-local)", "the mesh")
    lo, hi = src_lo - CROP_MARGIN_M, src_hi + CROP_MARGIN_M
    near_faces = f[faces_in_box(v, f, lo, hi)]
    tgt, nrm = mesh_registration_target(v, near_faces, target_spacing_m, TARGET_MAX_POINTS, cfg.seed)
    clock.lap("thin+target")
    return _register(src, tgt, nrm, cfg, rng, clock, t0)


def register_to_samples(source_xyz: np.ndarray, target_xyz: np.ndarray, target_normals: np.ndarray,
                        cfg: RegistrationConfig) -> RegistrationResult:
    """:func:`register_clouds` against surface samples made beforehand (the scan stage samples every mesh
    file once, so registration never re-reads a mesh): target_xyz (k, 3) float64 campus-local metres,
    target_normals (k, 3) their unit face normals, e.g. from :func:`mesh_registration_target`. The
    samples are cropped to the source's box grown by ``CROP_MARGIN_M`` and capped at
    ``TARGET_MAX_POINTS`` (a random subset, deterministic for ``cfg.seed``)."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(cfg.seed)
    clock = StepClock(t0)
    src = finite_xyz(source_xyz, "MLS point cloud", PRE_CAP_FACTOR * cfg.max_points, rng)
    src = subsample_for_registration(src, cfg.max_points, cfg.fine_voxel_m, rng)
    tgt, nrm = np.asarray(target_xyz, np.float64), np.asarray(target_normals, np.float64)
    src_lo, src_hi = src.min(axis=0), src.max(axis=0)
    check_overlap(src_lo, src_hi, tgt.min(axis=0), tgt.max(axis=0), "the MLS point cloud (campus-local)", "the mesh")
    keep = ((tgt >= src_lo - CROP_MARGIN_M) & (tgt <= src_hi + CROP_MARGIN_M)).all(axis=1)
    tgt, nrm = tgt[keep], nrm[keep]
    if len(tgt) > TARGET_MAX_POINTS:
        pick = np.sort(rng.choice(len(tgt), TARGET_MAX_POINTS, replace=False))
        tgt, nrm = tgt[pick], nrm[pick]
    clock.lap("thin+target")
    return _register(src, tgt, nrm, cfg, rng, clock, t0)


def _fitted_scale(matrix: np.ndarray) -> float:
    """The scale of a fitted similarity; FitFailed when the fit collapsed (not a proper similarity, or a
    scale outside :data:`SANE_SCALE`: Scale-ICP with no overlap can shrink the cloud onto one point)."""
    try:
        scale = decompose_similarity(matrix)[0]
    except ValueError as e:
        raise FitFailed(None, f"the fit collapsed ({e})") from None
    if not SANE_SCALE[0] <= scale <= SANE_SCALE[1]:
        raise FitFailed(None, f"the fit collapsed (scale {scale:.3g})")
    return scale


def _register(src, tgt, nrm, cfg: RegistrationConfig, rng, clock: StepClock, t0: float) -> RegistrationResult:
    """SAC-IA then Scale-ICP of the thinned source onto the surface samples (tgt, nrm)."""
    src_lo, src_hi = src.min(axis=0), src.max(axis=0)
    if len(tgt) < MIN_POINTS:
        raise InputError(
            None,
            f"the mesh surface within {CROP_MARGIN_M} m of the MLS cloud's extent "
            f"{np.round(src_lo, 1).tolist()} - {np.round(src_hi, 1).tolist()} gives {len(tgt)} samples "
            f"(need {MIN_POINTS}): the inputs do not overlap (wrong CRS, origin or units?)",
        )
    coarse, coarse_fit, coarse_info = coarse_register(src, tgt, cfg)
    clock.lap("coarse")

    near = _near(tgt, apply_similarity(coarse, src), FINE_CROP_M)
    tgt_f, nrm_f = tgt[near], nrm[near]
    if len(tgt_f) < MIN_POINTS:
        raise InputError(
            None,
            f"after the coarse registration only {len(tgt_f)} samples of the mesh surface lie within "
            f"{FINE_CROP_M} m of the MLS cloud (need {MIN_POINTS}): do the inputs overlap?",
        )
    if register_fine.FINE_METHOD == "plane":  # the switch lives with the fine stage
        tgt_f, nrm_f = surface_planes(tgt_f, nrm_f)  # face normals: see surface_planes
    clock.lap("fine-prep")
    matrix, fit, rmse, method = fine_register(src, tgt_f, nrm_f, coarse, cfg, rng)
    clock.lap("fine")
    if fit < LOW_FITNESS:  # the stage's guard (tasks.register.guard) turns this into its one warning line
        log.info("only %.0f %% of the MLS points lie within %s m of the mesh after registration: check the "
                    "result (do the inputs overlap? is the mesh badly degraded?)", 100 * fit, FINE_DISTANCES_M[-1])
    scale = _fitted_scale(matrix)
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
    "CoregistrationCheck",
    "RegistrationResult",
    "apply_similarity",
    "check_coregistered",
    "check_coregistered_samples",
    "check_overlap",
    "coarse_register",
    "compare_transforms",
    "compose_similarity",
    "consistent_matches",
    "crop_to_box",
    "decompose_similarity",
    "fine_register",
    "match_features",
    "mesh_registration_target",
    "plane_similarity_icp",
    "point_similarity_icp",
    "register_clouds",
    "register_to_samples",
    "subsample_for_registration",
    "surface_planes",
]
