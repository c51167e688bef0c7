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
ROTATION_PRIOR_DEG = (5.0, 5.0, 10.0)  # max |roll|, |pitch|, |yaw| (axis-angle components) of a hypothesis
NORMAL_RADIUS_VOXELS = 2.5  # normal estimation radius, in voxels
FPFH_RADIUS_VOXELS = 5.0  # FPFH radius, in voxels
SAC_MIN_THRESHOLD_VOXELS = 0.5  # RANSAC inlier distance is at least this many voxels (see coarse_register)
SAC_ATTEMPTS = 3  # independent RANSAC runs (different seeds); the best fitness wins
SAC_EVAL_POINTS = 5_000  # source voxels on which RANSAC scores a hypothesis
SAC_EVAL_HORIZONTAL_SHARE = 0.2  # at most this share of them on horizontal surfaces (see _eval_sample)
SAC_MAX_KEYPOINTS = (2_000, 6_000)  # FPFH keypoints (source, target), drawn among the most curved voxels
KEYPOINT_MIN_CURVATURE = 0.02  # surface variation l0 / (l0 + l1 + l2) of a keypoint (a plane is ~0)
SAC_CONSISTENT_MATCHES = 300  # matches kept for RANSAC, by degree in the compatibility graph
MAX_OFFSET_M = 10.0  # a feature match is only sought this far away (+ the rotation prior at that distance)
FINE_DISTANCES_M = (2.0, 1.0, 0.3, 0.15)  # ICP max correspondence distance schedule, metres
FINE_COARSE_POINTS = 60_000  # source points used in every ICP level but the last
FINE_LEVEL_ITERATIONS = 30  # iteration cap of every ICP level but the last (which uses cfg.icp_iterations)
FINE_MIN_KERNEL_M = 0.05  # floor of the adaptive Tukey kernel in the last ICP level (see fine_register)
FINE_CROP_M = 3.0  # fine stage keeps mesh vertices this near the coarsely aligned source
FINE_METHOD = "plane"  # "plane": point-to-plane similarity ICP; "point": Open3D point-to-point with scaling
SURFACE_NEIGHBOURS = 24  # mesh vertices averaged into one local plane (denoises ~5x)
SURFACE_SPACING_M = 0.2  # spacing of those planes (voxel-thinned vertices)
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


def _small_rotation(w: np.ndarray) -> np.ndarray:
    """(3,) rotation vector -> (3, 3) rotation (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-15:
        return np.eye(3)
    k = w / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


# --------------------------------------------------------------------------- input handling


class _Clock:
    """Wall and CPU seconds per named step (reported in RegistrationResult.details)."""

    def __init__(self, t0: float):
        self.t, self.c, self.laps = t0, time.process_time(), {}

    def lap(self, name: str) -> None:
        now, cpu = time.perf_counter(), time.process_time()
        self.laps[name] = (round(now - self.t, 2), round(cpu - self.c, 2))
        self.t, self.c = now, cpu


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
        a = np.asarray(_cloud(a).voxel_down_sample(voxel_m).points)
    if len(a) > max_points:
        a = a[np.sort(rng.choice(len(a), max_points, replace=False))]
    return a


def crop_to_box(xyz: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Boolean (n,) mask of points inside the axis-aligned box [lo, hi] ((3,) metres)."""
    return np.all((xyz >= lo) & (xyz <= hi), axis=1)


def _cloud(xyz: np.ndarray) -> o3d.geometry.PointCloud:
    return o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(xyz, dtype=np.float64)))


def _estimate_normals(pc: o3d.geometry.PointCloud, radius_m: float, viewpoint: np.ndarray) -> None:
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=30))
    # FPFH histograms change when a normal flips, so both clouds must orient alike: towards one
    # common viewpoint (above the MLS centroid, i.e. over the street), which also makes facade
    # normals point outwards, as a mesh's do.
    pc.orient_normals_towards_camera_location(viewpoint)


# --------------------------------------------------------------------------- coarse: SAC-IA


def _surface_variation(pc: o3d.geometry.PointCloud, radius_m: float) -> np.ndarray:
    """(n,) l0 / (l0 + l1 + l2) of each point's neighbourhood covariance: 0 on planes, ~0.1 on edges."""
    pc.estimate_covariances(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=30))
    ev = np.linalg.eigvalsh(np.asarray(pc.covariances))
    return ev[:, 0] / np.maximum(ev.sum(axis=1), 1e-18)


def _keypoints(
    pc: o3d.geometry.PointCloud, radius_m: float, cap: int, rng: np.random.Generator
) -> np.ndarray:
    """Indices (k,) int64 of curved points (edges, corners): at most ``cap``, drawn at random among them.

    A nearly planar cloud (fewer than ``MIN_POINTS`` curved points) falls back to its most curved points.
    """
    curv = _surface_variation(pc, radius_m)
    idx = np.flatnonzero(curv >= KEYPOINT_MIN_CURVATURE)
    if len(idx) < MIN_POINTS:
        idx = np.sort(np.argsort(curv)[-min(cap, len(curv)) :])
    if len(idx) > cap:
        idx = np.sort(rng.choice(idx, cap, replace=False))
    return idx


def match_features(
    src_xyz: np.ndarray, src_feat: np.ndarray, tgt_xyz: np.ndarray, tgt_feat: np.ndarray, gate_m: np.ndarray
) -> np.ndarray:
    """Nearest-descriptor match of each source point among the target points within its gate.

    src_xyz: (n, 3), src_feat: (n, d), tgt_xyz: (m, 3), tgt_feat: (m, d), gate_m: (n,) metres.
    Returns (k, 2) int64 pairs (source index, target index), at most one per source point (none
    for a source point with no target point within its gate).
    """
    tree = cKDTree(tgt_xyz)
    pairs = []
    for lo in range(0, len(src_xyz), 1000):
        hi = min(lo + 1000, len(src_xyz))
        lists = tree.query_ball_point(src_xyz[lo:hi], gate_m[lo:hi], workers=-1)
        counts = np.fromiter(map(len, lists), dtype=np.int64, count=hi - lo)
        if not counts.sum():
            continue
        i = np.repeat(np.arange(lo, hi), counts)  # sorted, so segments of one source point each
        j = np.concatenate([np.asarray(c, dtype=np.int64) for c in lists if c])
        diff = src_feat[i] - tgt_feat[j]
        d = np.einsum("ij,ij->i", diff, diff)
        starts = np.flatnonzero(np.r_[True, i[1:] != i[:-1]])
        best = starts + _segmented_argmin(d, starts)
        pairs.append(np.stack([i[best], j[best]], axis=1))
    return np.concatenate(pairs) if pairs else np.empty((0, 2), dtype=np.int64)


def _segmented_argmin(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """Offset (within its segment) of the minimum of each segment of ``values`` beginning at ``starts``."""
    mins = np.minimum.reduceat(values, starts)
    seg = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(values)]))
    hit = np.flatnonzero(values == mins[seg])
    first = np.r_[True, seg[hit][1:] != seg[hit][:-1]]
    return hit[first] - starts[seg[hit][first]]


def consistent_matches(
    src_xyz: np.ndarray, tgt_xyz: np.ndarray, tol_m: float, max_rotation_rad: float, keep: int
) -> np.ndarray:
    """Indices of the matches most consistent with the others under a small-rotation similarity.

    src_xyz, tgt_xyz: (k, 3) matched positions. Two true matches a, b of a similarity with a
    rotation below ``max_rotation_rad`` and a scale near 1 keep their distance (``| |p_a - p_b| -
    |q_a - q_b| | < tol_m + 1 % of it``) and nearly their displacement (``|(q_a - p_a) - (q_b - p_b)| <
    tol_m + 2 sin(max_rotation / 2) |p_a - p_b|``). Each match's degree in this compatibility graph
    ranks it; returns the indices of the ``keep`` best (int64, sorted by decreasing degree).
    """
    k = len(src_xyz)
    disp = tgt_xyz - src_xyz
    degree = np.zeros(k, dtype=np.int64)
    chord = 2.0 * np.sin(max_rotation_rad / 2.0)
    for lo in range(0, k, 512):
        hi = min(lo + 512, k)
        dp = np.linalg.norm(src_xyz[lo:hi, None] - src_xyz[None], axis=2)
        dq = np.linalg.norm(tgt_xyz[lo:hi, None] - tgt_xyz[None], axis=2)
        dd = np.linalg.norm(disp[lo:hi, None] - disp[None], axis=2)
        ok = (np.abs(dp - dq) < tol_m + 0.01 * dp) & (dd < tol_m + chord * dp)
        degree[lo:hi] = ok.sum(axis=1)
    return np.argsort(-degree, kind="stable")[: min(keep, k)]


def _eval_sample(idx: np.ndarray, normal_z: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` of ``idx`` at random, horizontal surfaces (|normal z| > 0.7) down-weighted.

    The ground, often most of an MLS cloud, fits any yaw and any horizontal shift, so a consensus
    scored mostly on it cannot tell a good hypothesis from a 2 degree one; at most
    ``SAC_EVAL_HORIZONTAL_SHARE`` of the scoring points are horizontal.
    """
    horizontal = np.abs(normal_z) > 0.7
    h, v = idx[horizontal], idx[~horizontal]
    n_h = min(len(h), max(int(SAC_EVAL_HORIZONTAL_SHARE * n), n - len(v)))
    n_v = min(len(v), n - n_h)
    return np.sort(np.concatenate([rng.choice(h, n_h, replace=False), rng.choice(v, n_v, replace=False)]))


def coarse_register(
    source_xyz: np.ndarray, target_xyz: np.ndarray, cfg: RegistrationConfig
) -> tuple[np.ndarray, float, dict]:
    """SAC-IA: FPFH features + sample consensus -> rigid (4, 4) source -> target.

    source_xyz, target_xyz: (n, 3) / (m, 3) float64 campus-local metres, already thinned and the
    target cropped around the source. Both are voxel-downsampled at ``cfg.voxel_m``; normals use a
    radius of ``NORMAL_RADIUS_VOXELS`` voxels and FPFH ``FPFH_RADIUS_VOXELS`` voxels.

    Matching. Descriptors are computed only at keypoints: voxels whose neighbourhood is curved
    (edges, corners; on planes every FPFH looks alike and only adds false matches). Each source
    keypoint takes the target keypoint with the nearest descriptor among those within
    ``MAX_OFFSET_M`` (+ what ``ROTATION_PRIOR_DEG`` moves a point at that distance from the data
    centroid): both clouds are in one campus frame, off by metres and degrees, and the gate turns
    a repetitive street into a solvable matching problem. On box streets ~5 % of these matches are
    right (a mutual filter kept ~350 matches at ~8 %); ranking them by their degree in a
    compatibility graph (:func:`consistent_matches`) and keeping ``SAC_CONSISTENT_MATCHES`` lifts
    that to ~18 %: ~6 all-inlier 3-samples expected in 1000 RANSAC iterations.

    Consensus. Open3D's RANSAC on these correspondences, ``cfg.sac_iterations`` iterations (paper:
    1000) per attempt, ``SAC_ATTEMPTS`` attempts seeded ``cfg.seed + attempt``, the best fitness
    wins. Hypotheses whose rotation exceeds ``ROTATION_PRIOR_DEG`` or whose sampled edges differ in
    length by > 10 % are rejected before scoring; scoring uses ``SAC_EVAL_POINTS`` source voxels.
    The paper's 10 cm (``cfg.sac_threshold_m``) is the inlier distance, but two independent voxel
    grids put their centroids up to ~half a voxel apart on one surface, so 10 cm on 0.3 m voxels
    counts only part of the true inliers. The distance used is ``max(cfg.sac_threshold_m,
    SAC_MIN_THRESHOLD_VOXELS * cfg.voxel_m)`` (15 cm by default). On a 120 m synthetic street the
    result is off by 0.25-1.9 deg and 0.1-1.2 m; the fine stage (2 m first level) converges there
    from at least 4 deg and 1.5 m.

    Returns (matrix, fitness, info): info holds the inlier distance, keypoint and match counts and
    the (wall, CPU) seconds of each step.
    """
    voxel = float(cfg.voxel_m)
    rng = np.random.default_rng(cfg.seed)
    clock = _Clock(time.perf_counter())
    centroid = source_xyz.mean(axis=0)
    src = _cloud(source_xyz).voxel_down_sample(voxel)
    tgt = _cloud(target_xyz).voxel_down_sample(voxel)
    if len(src.points) < MIN_POINTS or len(tgt.points) < MIN_POINTS:
        raise InputError(
            None,
            f"after {voxel} m voxels only {len(src.points)} MLS / {len(tgt.points)} mesh points remain "
            f"(need {MIN_POINTS}): the clouds are too small or do not overlap",
        )
    radius = NORMAL_RADIUS_VOXELS * voxel
    ks = _keypoints(src, radius, SAC_MAX_KEYPOINTS[0], rng)
    kt = _keypoints(tgt, radius, SAC_MAX_KEYPOINTS[1], rng)
    for pc in (src, tgt):  # reuses the covariances _keypoints left on the cloud
        _estimate_normals(pc, radius, centroid + np.array([0.0, 0.0, 5.0]))
    search = o3d.geometry.KDTreeSearchParamHybrid(radius=FPFH_RADIUS_VOXELS * voxel, max_nn=100)
    f_src = np.asarray(
        _reg.compute_fpfh_feature(src, search, o3d.utility.IntVector(ks.astype(np.int32))).data
    ).T
    f_tgt = np.asarray(
        _reg.compute_fpfh_feature(tgt, search, o3d.utility.IntVector(kt.astype(np.int32))).data
    ).T
    clock.lap("features")

    src_xyz, tgt_xyz = np.asarray(src.points), np.asarray(tgt.points)
    max_rot = np.radians(max(ROTATION_PRIOR_DEG))
    gate = MAX_OFFSET_M + np.sin(max_rot) * np.linalg.norm(src_xyz[ks] - centroid, axis=1)
    pairs = match_features(src_xyz[ks], f_src, tgt_xyz[kt], f_tgt, gate)
    n_matches = len(pairs)
    if n_matches < 3:
        raise InputError(None, "no FPFH matches between the MLS cloud and the mesh: do they overlap?")
    top = consistent_matches(
        src_xyz[ks[pairs[:, 0]]], tgt_xyz[kt[pairs[:, 1]]], 2.0 * voxel, max_rot, SAC_CONSISTENT_MATCHES
    )
    pairs = pairs[top]
    clock.lap("matching")

    # hypotheses are scored on the matched keypoints plus random other source voxels
    matched = ks[pairs[:, 0]]
    others = np.setdiff1d(np.arange(len(src_xyz)), matched)
    n_more = max(0, min(len(others), SAC_EVAL_POINTS - len(matched)))
    pick = _eval_sample(others, np.asarray(src.normals)[others, 2], n_more, rng)
    src_eval = _cloud(np.concatenate([src_xyz[matched], src_xyz[pick]]))
    corres = o3d.utility.Vector2iVector(
        np.stack([np.arange(len(matched)), kt[pairs[:, 1]]], axis=1).astype(np.int32)
    )
    distance = max(float(cfg.sac_threshold_m), SAC_MIN_THRESHOLD_VOXELS * voxel)
    checkers = [
        _reg.CorrespondenceCheckerBasedOnEdgeLength(0.9),
        _reg.CorrespondenceCheckerBasedOnSourceRotation(np.radians(ROTATION_PRIOR_DEG).reshape(3, 1)),
        _reg.CorrespondenceCheckerBasedOnDistance(distance),
    ]
    best = None
    for attempt in range(SAC_ATTEMPTS):
        o3d.utility.random.seed(int(cfg.seed) + attempt)
        res = _reg.registration_ransac_based_on_correspondence(
            src_eval,
            tgt,
            corres,
            distance,
            _reg.TransformationEstimationPointToPoint(False),
            3,
            checkers,
            _reg.RANSACConvergenceCriteria(int(cfg.sac_iterations), 0.9999),
        )
        if best is None or (res.fitness, -res.inlier_rmse) > (best.fitness, -best.inlier_rmse):
            best = res
    clock.lap("ransac")
    info = {
        "inlier_distance_m": distance,
        "keypoints": (len(ks), len(kt)),
        "matches": (n_matches, len(pairs)),
        "seconds": clock.laps,
    }
    return np.asarray(best.transformation).copy(), float(best.fitness), info


# --------------------------------------------------------------------------- fine: Scale-ICP


def _box_corners(xyz: np.ndarray) -> np.ndarray:
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    return np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])


def _max_motion(delta: np.ndarray, corners: np.ndarray) -> float:
    """Largest displacement, metres, that the (4, 4) update ``delta`` gives the data's bbox corners."""
    return float(np.linalg.norm(apply_similarity(delta, corners) - corners, axis=1).max())


def plane_similarity_icp(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    target_normals: np.ndarray,
    init: np.ndarray,
    max_distance_m: float,
    max_iterations: int,
    tolerance_m: float,
    with_scale: bool = True,
    tree: cKDTree | None = None,
    kernel_m: float | None = None,
    min_kernel_m: float = 0.01,
) -> tuple[np.ndarray, float, float, int]:
    """Point-to-plane ICP estimating a similarity (Gauss-Newton on 7 parameters, Tukey-weighted).

    source_xyz: (n, 3); target_xyz, target_normals: (m, 3) points and unit normals of planes on the
    target surface (:func:`surface_planes`); float64 metres. init: (4, 4) source -> target. Each
    iteration pairs every transformed source point with its nearest plane (by its point) within
    ``max_distance_m`` and minimises ``sum w (n . (s R p + t - q))^2``
    over a rotation, translation and (with ``with_scale``) a scale about the paired points'
    centroid, linearised. Weights: Tukey biweight with c = ``kernel_m``, or when None adaptively
    4.685 x 1.4826 x median |residual| (clipped to [``min_kernel_m``, ``max_distance_m``]). Stops when an update moves no corner of the source
    bounding box by more than ``tolerance_m`` or after ``max_iterations``.

    Measuring the residual along the normal makes it insensitive to where on the surface the paired
    plane point lies; point-to-point ICP to ~10 cm spaced, noisy vertices is not.
    Returns (matrix, fitness, rmse_m, iterations): fitness = share of source points paired, rmse =
    RMS point-to-plane residual of the paired points under the returned matrix.
    """
    tree = cKDTree(target_xyz) if tree is None else tree
    m = np.asarray(init, dtype=np.float64).copy()
    corners = _box_corners(source_xyz)
    it = 0
    for it in range(1, max_iterations + 1):
        p = apply_similarity(m, source_xyz)
        dist, idx = tree.query(p, distance_upper_bound=max_distance_m, workers=-1)
        ok = np.isfinite(dist)
        if ok.sum() < 10:
            raise InputError(
                None, f"ICP lost the overlap: {int(ok.sum())} source points within {max_distance_m} m"
            )
        p, q, nrm = p[ok], target_xyz[idx[ok]], target_normals[idx[ok]]
        r = np.einsum("ij,ij->i", p - q, nrm)
        c = kernel_m
        if c is None:
            c = np.clip(4.685 * 1.4826 * np.median(np.abs(r)), min_kernel_m, max_distance_m)
        w = np.where(np.abs(r) < c, (1.0 - (r / c) ** 2) ** 2, 0.0)
        if w.sum() <= 0:
            break
        c0 = (w[:, None] * p).sum(axis=0) / w.sum()
        a = p - c0
        cols = [np.cross(a, nrm), nrm]
        if with_scale:
            cols.append(np.einsum("ij,ij->i", a, nrm)[:, None])
        jac = np.concatenate(cols, axis=1)
        jw = jac * w[:, None]
        h = jw.T @ jac
        h += 1e-9 * np.trace(h) * np.eye(len(h))  # keeps an unobservable direction from exploding
        x = np.linalg.solve(h, -(jw.T @ r))
        ds = x[6] if with_scale else 0.0
        step = np.eye(4)
        step[:3, :3] = (1.0 + ds) * _small_rotation(x[:3])
        step[:3, 3] = c0 + x[3:6] - step[:3, :3] @ c0
        moved = _max_motion(step, apply_similarity(m, corners))
        m = step @ m
        if moved < tolerance_m:
            break
    p = apply_similarity(m, source_xyz)
    dist, idx = tree.query(p, distance_upper_bound=max_distance_m, workers=-1)
    ok = np.isfinite(dist)
    r = np.einsum("ij,ij->i", p[ok] - target_xyz[idx[ok]], target_normals[idx[ok]])
    rmse = float(np.sqrt(np.mean(r**2))) if ok.any() else float("nan")
    return m, float(ok.mean()), rmse, it


def point_similarity_icp(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    init: np.ndarray,
    max_distance_m: float,
    max_iterations: int,
    with_scale: bool = True,
) -> tuple[np.ndarray, float, float, int]:
    """Open3D point-to-point ICP, with scaling (the paper's Scale-ICP as Open3D implements it).

    Same arrays and return as :func:`plane_similarity_icp` (rmse is point-to-point here; iterations
    is not reported by Open3D, -1). Converges on relative fitness / RMSE changes of 1e-6.
    """
    res = _reg.registration_icp(
        _cloud(source_xyz),
        _cloud(target_xyz),
        max_distance_m,
        np.asarray(init, dtype=np.float64),
        _reg.TransformationEstimationPointToPoint(with_scale),
        _reg.ICPConvergenceCriteria(
            relative_fitness=1e-6, relative_rmse=1e-6, max_iteration=int(max_iterations)
        ),
    )
    return np.asarray(res.transformation).copy(), float(res.fitness), float(res.inlier_rmse), -1


def surface_planes(
    xyz: np.ndarray,
    normals: np.ndarray | None = None,
    k: int = SURFACE_NEIGHBOURS,
    spacing_m: float = SURFACE_SPACING_M,
) -> tuple[np.ndarray, np.ndarray]:
    """Denoised local planes through a noisy vertex set, about ``spacing_m`` apart.

    xyz: (m, 3) float64 metres (mesh vertices, ~10 cm apart with a few cm of noise);
    normals: optional (m, 3) vertex normals to use instead of the estimated ones.
    The vertices are voxel-thinned at ``spacing_m`` (<= 0: every vertex); at each thinned point a
    plane is fitted to its ``k`` nearest original vertices. Returns (centres, normals), both
    (m', 3) float64: the mean of those neighbours and their direction of least spread (unit, sign
    arbitrary; with ``normals`` given, the normal of the nearest vertex).
    Pairing an MLS point with such a plane instead of a raw vertex divides the vertex noise by
    ~sqrt(k), so the ICP's robust weights can tell a real mesh defect (a facade 15 cm proud) from
    noise.
    """
    tree = cKDTree(xyz)
    query = np.asarray(_cloud(xyz).voxel_down_sample(spacing_m).points) if spacing_m > 0 else xyz
    k = min(k, len(xyz))
    centres, out = np.empty_like(query), np.empty_like(query)
    for lo in range(0, len(query), 100_000):
        hi = min(lo + 100_000, len(query))
        _, idx = tree.query(query[lo:hi], k=k, workers=-1)
        nb = xyz[idx]
        c = nb.mean(axis=1)
        d = nb - c[:, None]
        centres[lo:hi] = c
        if normals is None:
            out[lo:hi] = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d))[1][:, :, 0]
        else:
            n = normals[idx[:, 0]]
            out[lo:hi] = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return centres, out


def fine_register(
    source_xyz: np.ndarray,
    target_xyz: np.ndarray,
    target_normals: np.ndarray,
    init: np.ndarray,
    cfg: RegistrationConfig,
    rng: np.random.Generator,
) -> tuple[np.ndarray, float, float, str]:
    """Scale-ICP from a coarse alignment, over the distance schedule ``FINE_DISTANCES_M``.

    source_xyz: (n, 3) thinned MLS points; target_xyz/target_normals: (m, 3) points and unit normals
    of the mesh near the source (the :func:`surface_planes` of its vertices for the "plane" method,
    the raw vertices for "point", which ignores the normals); init: (4, 4) coarse source -> target;
    all float64 campus-local metres.

    Every level but the last runs at most ``FINE_LEVEL_ITERATIONS`` iterations on
    ``FINE_COARSE_POINTS`` random source points, with a Tukey kernel as wide as its distance; the
    last uses all of them, ``cfg.icp_iterations`` (paper: 1000) and a kernel adapted to the
    residuals but not below ``FINE_MIN_KERNEL_M``. (A kernel adapted from the start let the
    facades, the majority, converge first and then reject the whole ground as outliers, freezing
    the height 10 cm off: vertical facades do not constrain it.) The paper's "1 mm" (``cfg.icp_threshold_m``) cannot be a
    correspondence distance here: mesh vertices are ~10 cm apart and carry a few cm of noise, so
    almost no MLS point has a vertex within 1 mm. It is used as the convergence threshold instead:
    a level ends when one update moves no corner of the source's bounding box by more than 1 mm.

    Measured on a synthetic street (truth yaw 3 deg, t 2.5 m, scale 1.003; mesh vertices 10 cm
    apart), errors in rotation / translation at the centroid / scale:
    2 cm vertex noise: "plane" 0.0005 deg / 0.1 mm / 0.0004 %, "point" 0.006 deg / 0.8 mm / 0.001 %;
    5 cm noise + one facade 15 cm proud + a hole: "plane" 0.002 deg / 0.5 mm / 0.001 %, "point"
    0.046 deg / 36 mm / 0.14 % (0.012 deg / 5 mm / 0.05 % with an extra 3 cm level, 8x slower);
    "plane" against raw vertices instead of surface_planes: 0.050 deg / 28 mm / 0.12 %.

    Returns (matrix, fitness, rmse_m, method name).
    """
    small = source_xyz
    if len(source_xyz) > FINE_COARSE_POINTS:
        small = source_xyz[np.sort(rng.choice(len(source_xyz), FINE_COARSE_POINTS, replace=False))]
    tree = cKDTree(target_xyz) if FINE_METHOD == "plane" else None
    m = np.asarray(init, dtype=np.float64)
    fit = rmse = float("nan")
    for level, dist in enumerate(FINE_DISTANCES_M):
        last = level == len(FINE_DISTANCES_M) - 1
        pts = source_xyz if last else small
        iters = int(cfg.icp_iterations) if last else min(FINE_LEVEL_ITERATIONS, int(cfg.icp_iterations))
        if FINE_METHOD == "plane":
            m, fit, rmse, _ = plane_similarity_icp(
                pts,
                target_xyz,
                target_normals,
                m,
                dist,
                iters,
                float(cfg.icp_threshold_m),
                cfg.with_scale,
                tree,
                kernel_m=None if last else dist,
                min_kernel_m=FINE_MIN_KERNEL_M,
            )
        else:
            m, fit, rmse, _ = point_similarity_icp(pts, target_xyz, m, dist, iters, cfg.with_scale)
    return m, fit, rmse, f"{FINE_METHOD}-scale-icp" if cfg.with_scale else f"{FINE_METHOD}-icp"


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
    pc = _cloud(xyz)
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
    clock = _Clock(t0)
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
