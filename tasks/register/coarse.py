"""Coarse registration: SAC-IA (FPFH features at curved keypoints + sample consensus), Liu et al. 2023, 3.1.

The paper registers in two steps; this is the first (1000 iterations, 10 cm): a rigid transform good to
a few decimetres and a degree or two, from which the fine stage (:mod:`tasks.register.fine`) converges.
See :func:`coarse_register`. Arrays are float64 campus-local metres.
"""

from __future__ import annotations

import time

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from storage.errors import InputError
from tasks.config import RegistrationConfig
from tasks.register.base import MIN_POINTS, StepClock, o3d_cloud
from tasks.register.sac import SacResult, sac_register

_reg = o3d.pipelines.registration

# Parameters not (yet) in RegistrationConfig; candidates for config fields.
ROTATION_PRIOR_DEG = (5.0, 5.0, 10.0)  # max |roll|, |pitch|, |yaw| (axis-angle components) of a hypothesis
NORMAL_RADIUS_VOXELS = 2.5  # normal estimation radius, in voxels
FPFH_RADIUS_VOXELS = 5.0  # FPFH radius, in voxels
SAC_MIN_THRESHOLD_VOXELS = 0.5  # RANSAC inlier distance is at least this many voxels (see coarse_register)
SAC_ATTEMPTS = 3  # hypotheses drawn: SAC_ATTEMPTS x cfg.sac_iterations (once three Open3D runs)
SAC_EVAL_POINTS = 5_000  # source voxels on which RANSAC scores a hypothesis
SAC_EVAL_HORIZONTAL_SHARE = 0.2  # at most this share of them on horizontal surfaces (see _eval_sample)
SAC_MAX_KEYPOINTS = (2_000, 6_000)  # FPFH keypoints (source, target), drawn among the most curved voxels
KEYPOINT_MIN_CURVATURE = 0.02  # surface variation l0 / (l0 + l1 + l2) of a keypoint (a plane is ~0)
SAC_CONSISTENT_MATCHES = 300  # matches kept for RANSAC, by degree in the compatibility graph
MAX_OFFSET_M = 10.0  # a feature match is only sought this far away (+ the rotation prior at that distance)


def _estimate_normals(pc: o3d.geometry.PointCloud, radius_m: float, viewpoint: np.ndarray) -> None:
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=radius_m, max_nn=30))
    # FPFH histograms change when a normal flips, so both clouds must orient alike: towards one
    # common viewpoint (above the MLS centroid, i.e. over the street), which also makes facade
    # normals point outwards, as a mesh's do.
    pc.orient_normals_towards_camera_location(viewpoint)


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

    Consensus (:mod:`tasks.register.sac`, reproducible run to run, unlike Open3D's threaded RANSAC):
    ``cfg.sac_iterations`` hypotheses (paper: 1000) times ``SAC_ATTEMPTS``, seeded ``cfg.seed``; the best
    fitness wins. Hypotheses whose rotation exceeds ``ROTATION_PRIOR_DEG`` or whose sampled edges differ in
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
    clock = StepClock(time.perf_counter())
    centroid = source_xyz.mean(axis=0)
    src, tgt = (_voxel_cloud(xyz, voxel) for xyz in (source_xyz, target_xyz))
    if len(src.points) < MIN_POINTS or len(tgt.points) < MIN_POINTS:
        raise InputError(
            None,
            f"after {voxel} m voxels only {len(src.points)} MLS / {len(tgt.points)} mesh points remain "
            f"(need {MIN_POINTS}): the clouds are too small or do not overlap",
        )
    ks, kt, f_src, f_tgt = _keypoint_features(src, tgt, voxel, centroid, rng)
    clock.lap("features")

    src_xyz, tgt_xyz = np.asarray(src.points), np.asarray(tgt.points)
    pairs, n_matches = _gated_matches(src_xyz, tgt_xyz, ks, kt, f_src, f_tgt, centroid, voxel)
    clock.lap("matching")

    # hypotheses are scored on the matched keypoints plus random other source voxels
    matched = ks[pairs[:, 0]]
    others = np.setdiff1d(np.arange(len(src_xyz)), matched)
    n_more = max(0, min(len(others), SAC_EVAL_POINTS - len(matched)))
    pick = _eval_sample(others, np.asarray(src.normals)[others, 2], n_more, rng)
    src_eval = o3d_cloud(np.concatenate([src_xyz[matched], src_xyz[pick]]))
    corres = np.stack([np.arange(len(matched)), kt[pairs[:, 1]]], axis=1).astype(np.int32)
    distance = max(float(cfg.sac_threshold_m), SAC_MIN_THRESHOLD_VOXELS * voxel)
    best = _best_ransac(src_eval, tgt, corres, distance, cfg)
    clock.lap("ransac")
    info = {
        "inlier_distance_m": distance,
        "keypoints": (len(ks), len(kt)),
        "matches": (n_matches, len(pairs)),
        "seconds": clock.laps,
    }
    return np.asarray(best.transformation).copy(), float(best.fitness), info


def _voxel_cloud(xyz: np.ndarray, voxel_m: float) -> o3d.geometry.PointCloud:
    """xyz (n, 3) float64 metres as an Open3D cloud of voxel centroids (``voxel_m`` voxels)."""
    return o3d_cloud(xyz).voxel_down_sample(voxel_m)


def _keypoint_features(src, tgt, voxel: float, centroid: np.ndarray, rng: np.random.Generator):
    """Curved keypoints of both voxel clouds and their FPFH descriptors: (ks (a,) int64, kt (b,) int64,
    f_src (a, 33), f_tgt (b, 33)). Estimates the clouds' normals (oriented towards a point 5 m above
    ``centroid``), which scoring uses later."""
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
    return ks, kt, f_src, f_tgt


def _gated_matches(src_xyz, tgt_xyz, ks, kt, f_src, f_tgt, centroid, voxel: float) -> tuple[np.ndarray, int]:
    """Keypoint matches within the spatial gate, the ``SAC_CONSISTENT_MATCHES`` most consistent kept:
    ((k, 2) int64 (index into ks, index into kt), number of gated matches before the consistency cut)."""
    max_rot = np.radians(max(ROTATION_PRIOR_DEG))
    gate = MAX_OFFSET_M + np.sin(max_rot) * np.linalg.norm(src_xyz[ks] - centroid, axis=1)
    pairs = match_features(src_xyz[ks], f_src, tgt_xyz[kt], f_tgt, gate)
    n_matches = len(pairs)
    if n_matches < 3:
        raise InputError(None, "no FPFH matches between the MLS cloud and the mesh: do they overlap?")
    top = consistent_matches(
        src_xyz[ks[pairs[:, 0]]], tgt_xyz[kt[pairs[:, 1]]], 2.0 * voxel, max_rot, SAC_CONSISTENT_MATCHES
    )
    return pairs[top], n_matches


def _best_ransac(src_eval, tgt, corres: np.ndarray, distance: float, cfg: RegistrationConfig) -> SacResult:
    """Sample consensus on the correspondences (:func:`tasks.register.sac.sac_register`, reproducible run to
    run): ``SAC_ATTEMPTS * cfg.sac_iterations`` hypotheses seeded ``cfg.seed``, pruned by edge length (0.9),
    the rotation prior and the inlier distance; the best (fitness, then lowest inlier RMSE) wins.
    corres: (k, 2) int32 (row of src_eval, index into tgt)."""
    return sac_register(np.asarray(src_eval.points), np.asarray(tgt.points), corres, distance, seed=int(cfg.seed),
                        n_hypotheses=SAC_ATTEMPTS * int(cfg.sac_iterations),
                        max_rotation_rad=np.radians(ROTATION_PRIOR_DEG))
