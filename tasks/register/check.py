"""Do the MLS cloud and the mesh already coincide? Do they overlap at all?

:func:`check_overlap` compares x/y extents (cheap, from file headers) and raises a clear InputError
when they are disjoint: a mesh 10 km off, a wrong UTM zone or mesh offset. :func:`check_coregistered`
(used when registration is switched off) measures exact point-to-surface distances from a thinned
sample of the MLS cloud to the mesh triangles, on the part of the sample that lies over the mesh.
Both work for any tessellation: a coarse LoD2-like model with a few hundred large triangles is
measured as exactly as a dense photogrammetric mesh.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import open3d as o3d

from storage.errors import InputError
from tasks.geometry.distance import point_to_mesh_distance
from tasks.register.base import PRE_CAP_FACTOR, finite_xyz, o3d_cloud, subsample_for_registration
from tasks.register.target import faces_in_box, mesh_arrays, used_bounds

CHECK_POINTS = 50_000  # source points sampled by check_coregistered
CHECK_VOXEL_M = 0.2  # ... after thinning at this voxel size
CHECK_MIN_GROUP_SHARE = 0.05  # an orientation group counts in check_coregistered from this share of points
CHECK_CROP_M = 10.0  # distances are measured to the faces within this much of the measured points' box
CHECK_TOL_M = 0.2  # default tolerance on the robust median distance


@dataclass(frozen=True)
class CoregistrationCheck:
    """How far a thinned sample of the MLS cloud lies from the mesh surface (metres).

    ok: ``median_m <= tol_m``. median_m: the largest median over the surface-orientation groups
    (see :func:`check_coregistered`); p90_m: 90th percentile over all measured points; both NaN
    when no sampled point lies over the mesh. overlap_fraction: share of the sample over the mesh's
    x/y extent (the points measured). n_points: points measured; n_sample: points in the sample.
    """

    ok: bool
    median_m: float
    p90_m: float
    overlap_fraction: float
    n_points: int
    n_sample: int
    tol_m: float

    def to_json(self) -> dict:
        """Plain values; NaN becomes None."""
        return {k: (None if isinstance(x, float) and math.isnan(x) else x) for k, x in asdict(self).items()}

    def __str__(self) -> str:
        if self.n_points == 0:
            return f"none of {self.n_sample:,} sampled MLS points lies over the mesh's x/y extent"
        return (
            f"MLS points lie a median {self.median_m:.3f} m from the mesh surface on their worst-placed "
            f"surface orientation (tolerance {self.tol_m} m; 90 % of all within {self.p90_m:.3f} m), measured "
            f"on {self.n_points:,} points over the mesh ({100 * self.overlap_fraction:.0f} % of the sample)"
        )


def _extent(lo, hi) -> str:
    return f"x {lo[0]:,.0f}..{hi[0]:,.0f}, y {lo[1]:,.0f}..{hi[1]:,.0f}"


def check_overlap(
    source_lo,
    source_hi,
    mesh_lo,
    mesh_hi,
    source_name: str = "the MLS point cloud",
    mesh_name: str = "the mesh",
) -> None:
    """Raise InputError when the x/y boxes of the point cloud and the mesh do not overlap at all.

    source_lo/hi, mesh_lo/hi: (2,) or (3,) box corners, metres, in one frame (pass world
    coordinates, as read from the file headers, so the message names places the user recognises).
    The message is one sentence naming both extents, rounded to metres. Touching boxes overlap.

    >>> check_overlap((0, 0), (10, 10), (5, 5), (20, 20))
    >>> check_overlap((500000, 0), (500100, 10), (510000, 0), (510100, 10), "scan.laz", "city.obj")
    ... # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    storage.errors.InputError: the x/y extents of scan.laz (x 500,000..500,100, y 0..10) and city.obj (x 510,000...
    """
    s_lo, s_hi, m_lo, m_hi = (np.asarray(b, np.float64)[:2] for b in (source_lo, source_hi, mesh_lo, mesh_hi))
    if not all(np.isfinite(b).all() for b in (s_lo, s_hi, m_lo, m_hi)):
        raise InputError(None, f"unknown extent: {source_name} {s_lo}..{s_hi}, {mesh_name} {m_lo}..{m_hi}")
    if (s_lo <= m_hi).all() and (m_lo <= s_hi).all():
        return
    raise InputError(
        None,
        f"the x/y extents of {source_name} ({_extent(s_lo, s_hi)}) and {mesh_name} ({_extent(m_lo, m_hi)}) "
        "do not overlap: wrong CRS or UTM zone, units, or mesh offset?",
    )


def _orientation_groups(xyz: np.ndarray) -> np.ndarray:
    """(n, 13) bool membership of each point's surface in the orientation groups: column 0 horizontal
    (|normal z| > 0.7); columns 1..12 vertical, normal azimuth within 15 deg of 0, 15, ..., 165 deg.

    The vertical bins overlap (30 deg wide, every 15 deg), so a wall of any azimuth lies wholly in one
    of them: with disjoint bins, a wall whose normal lies on a bin edge (x-facing walls with edges at
    0 / 180 deg) is split by normal noise into two halves that may each fall below the share a group
    needs, and a shift across that wall goes unseen.
    """
    pc = o3d_cloud(xyz)
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    n = np.asarray(pc.normals)
    horizontal = np.abs(n[:, 2]) > 0.7
    azimuth = np.degrees(np.arctan2(n[:, 1], n[:, 0]))
    apart = np.abs((azimuth[:, None] - np.arange(0.0, 180.0, 15.0) + 90.0) % 180.0 - 90.0)
    return np.concatenate([horizontal[:, None], (apart <= 15.0) & ~horizontal[:, None]], axis=1)


def check_coregistered(
    source_xyz: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    tol_m: float = CHECK_TOL_M,
    seed: int = 0,
) -> CoregistrationCheck:
    """Does the MLS cloud already lie on the mesh surface? (Used when registration is switched off.)

    source_xyz: (n, 3) MLS points; vertices: (m, 3); faces: (k, 3) int64; float64 campus-local metres.
    The source is thinned (``CHECK_VOXEL_M`` voxels, at most ``CHECK_POINTS``); the points over the
    mesh's x/y extent are measured, each by its exact distance to the nearest triangle (faces within
    ``CHECK_CROP_M`` of those points). A plain median would hide a shift along the dominant surfaces
    (across a street, the ground and the side walls do not move away from the mesh, and they can be
    most of the points), so points are grouped by surface orientation (horizontal; vertical in
    overlapping 30 degree azimuth bins, see ``_orientation_groups``) and the largest median over the
    groups holding at least ``CHECK_MIN_GROUP_SHARE`` of the measured points is reported. A shift
    parallel to every well-populated surface family stays invisible.

    Raises InputError when the x/y extents do not overlap at all (:func:`check_overlap`, campus-local
    coordinates) or an input is unusable.
    """
    rng = np.random.default_rng(seed)
    v, f = mesh_arrays(vertices, faces)
    mesh_lo, mesh_hi = used_bounds(v, f)
    pts, n_sample = _points_over(source_xyz, mesh_lo, mesh_hi, rng)
    if len(pts) == 0:
        return CoregistrationCheck(False, math.nan, math.nan, 0.0, 0, n_sample, float(tol_m))
    lo, hi = pts.min(axis=0) - CHECK_CROP_M, pts.max(axis=0) + CHECK_CROP_M
    if not ((lo <= mesh_lo).all() and (mesh_hi <= hi).all()):  # else every face is near
        near = faces_in_box(v, f, lo, hi)
        f = f[near] if len(near) else f
    dist = point_to_mesh_distance(pts, v, f)
    return _summarise(pts, dist, n_sample, tol_m)


def _points_over(source_xyz: np.ndarray, mesh_lo: np.ndarray, mesh_hi: np.ndarray,
                 rng: np.random.Generator) -> tuple[np.ndarray, int]:
    """The thinned MLS points over the mesh's x/y extent: ((m, 3) float64, size of the thinned sample).
    Raises InputError when the extents do not overlap at all."""
    src = finite_xyz(source_xyz, "MLS point cloud", PRE_CAP_FACTOR * CHECK_POINTS, rng)
    check_overlap(src.min(axis=0), src.max(axis=0), mesh_lo, mesh_hi,
                  "the MLS point cloud (campus-local)", "the mesh")  # fmt: skip
    src = subsample_for_registration(src, CHECK_POINTS, CHECK_VOXEL_M, rng)
    over = ((src[:, :2] >= mesh_lo[:2]) & (src[:, :2] <= mesh_hi[:2])).all(axis=1)
    return src[over], len(src)


def _summarise(pts: np.ndarray, dist: np.ndarray, n_sample: int, tol_m: float) -> CoregistrationCheck:
    """The check's figures from the measured points (m, 3) and their distances (m,) to the surface."""
    groups = _orientation_groups(pts) if len(pts) >= 20 else np.ones((len(pts), 1), bool)
    big = np.flatnonzero(groups.sum(axis=0) >= CHECK_MIN_GROUP_SHARE * len(pts))
    medians = [np.median(dist[groups[:, g]]) for g in big]
    worst = float(max(medians)) if medians else float(np.median(dist))
    return CoregistrationCheck(
        ok=worst <= tol_m,
        median_m=worst,
        p90_m=float(np.percentile(dist, 90)),
        overlap_fraction=float(len(pts) / n_sample),
        n_points=len(pts),
        n_sample=n_sample,
        tol_m=float(tol_m),
    )


def check_coregistered_samples(
    source_xyz: np.ndarray,
    samples_xyz: np.ndarray,
    samples_normal: np.ndarray,
    tol_m: float = CHECK_TOL_M,
    seed: int = 0,
    reach_m: float = 1.0,
) -> CoregistrationCheck:
    """:func:`check_coregistered` against area-weighted surface samples with their face normals (what the
    scan stage keeps of every mesh), so the check needs no mesh re-read.

    samples_xyz, samples_normal: (k, 3) float64 campus-local metres / unit normals. Each measured point's
    distance is its distance to the *plane* of its nearest sample (exact on planar faces, whatever the
    sample spacing); a point with no sample within ``reach_m`` counts at its distance to that sample.
    """
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    tgt = np.asarray(samples_xyz, np.float64)
    nrm = np.asarray(samples_normal, np.float64)
    pts, n_sample = _points_over(source_xyz, tgt.min(axis=0), tgt.max(axis=0), rng)
    if len(pts) == 0:
        return CoregistrationCheck(False, math.nan, math.nan, 0.0, 0, n_sample, float(tol_m))
    near, idx = cKDTree(tgt).query(pts, workers=-1)
    plane = np.abs(((pts - tgt[idx]) * nrm[idx]).sum(axis=1))
    dist = np.where(near <= reach_m, plane, near)
    return _summarise(pts, dist, n_sample, tol_m)

__all__ = ["CHECK_TOL_M", "CoregistrationCheck", "check_coregistered", "check_coregistered_samples", "check_overlap"]
