"""Vehicle trajectories of a simulated mobile-mapping campaign, with a GNSS/INS error model.

A :class:`Trajectory` is one pass of the vehicle along one road: the right-hand lane of the road
centre line (centre-line corners rounded to ``corner_radius_m``, then offset ``lane_offset_m`` to
the right of the driving direction), driven at constant speed. Passes alternate direction (0 forward, 1 back, ...),
as a real campaign drives a street both ways. GPS time is seconds of the GPS week, monotonic over
all passes of all roads (passes follow each other with a gap).

Positions are the vehicle reference point *on the road surface* (z from the truth mesh under the
lane, or 0); scanner heads and cameras are mounted above it (``synth.mls``, ``synth.cameras``).

Error model (what georeferencing gets wrong): the recorded trajectory is the true one plus
``error_at(t)`` = a constant per-pass 3D offset (1-5 cm between passes) + a slow linear drift + a
low-frequency wander of ~12 mm RMS per axis (sum of sinusoids, periods 0.5-3 s; with the MLS
heads' range bias it lifts flat-wall noise over one pass to ~10 mm, the real-data figure). Sensors are simulated from
the true pose; their outputs are shifted by ``error_at(t)``. All in the mesh frame: campus-local
metres, float64, z up.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .scene import Mesh


@dataclass(frozen=True)
class TrajectoryParams:
    """How the vehicle drives, and how wrong its recorded pose is."""

    speed_m_s: float = 9.0
    lane_offset_m: float = 2.0  # right of the road centre line
    n_passes: int = 2
    alternate_direction: bool = True
    corner_radius_m: float = 8.0
    max_step_m: float = 2.0  # path vertices at most this far apart (follows the terrain)
    gps_start_s: float = 302_400.0  # seconds of GPS week (Wednesday 12:00)
    pass_gap_s: float = 30.0
    pass_offset_m: tuple[float, float] = (0.005, 0.025)  # |constant offset| per pass, uniform
    drift_m_per_s: float = 1.0e-4  # max |drift| (1 cm per 100 s)
    jitter_m: float = 0.012  # per-axis RMS of the low-frequency wander
    jitter_period_s: tuple[float, float] = (0.5, 3.0)
    n_jitter_terms: int = 6


@dataclass
class Trajectory:
    """One pass along one road.

    path: (k, 3) float64 lane polyline in driving order (metres, mesh frame, z = road surface);
    s: (k,) float64 cumulative arc length (horizontal, metres); t_start/t_end: GPS seconds of week.
    offset_m: (3,) constant error; drift_m_per_s: (3,) error growth; jitter_amp_m: (j, 3),
    jitter_freq_hz: (j,), jitter_phase: (j, 3) radians: the recorded pose is true + error_at(t).
    """

    traj_id: int
    road_id: int
    pass_id: int
    direction: int  # +1 along the road polyline, -1 against it
    path: np.ndarray
    s: np.ndarray
    speed_m_s: float
    t_start: float
    offset_m: np.ndarray
    drift_m_per_s: np.ndarray
    jitter_amp_m: np.ndarray
    jitter_freq_hz: np.ndarray
    jitter_phase: np.ndarray

    @property
    def length_m(self) -> float:
        return float(self.s[-1])

    @property
    def duration_s(self) -> float:
        return self.length_m / self.speed_m_s

    @property
    def t_end(self) -> float:
        return self.t_start + self.duration_s

    def pose_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """True pose at GPS times ``t`` (n,) float64 -> (xyz (n, 3) float64, heading (n,) float64).

        heading: radians, counter-clockwise from +x (east), the driving direction; it is
        interpolated between segment mid-points so it turns smoothly through rounded corners.
        Times outside [t_start, t_end] are clamped to the ends.
        """
        sq = np.clip((np.asarray(t, np.float64) - self.t_start) * self.speed_m_s, 0.0, self.s[-1])
        xyz = np.stack([np.interp(sq, self.s, self.path[:, i]) for i in range(3)], axis=1)
        d = np.diff(self.path[:, :2], axis=0)
        seg_heading = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
        mid = 0.5 * (self.s[1:] + self.s[:-1])
        return xyz, np.interp(sq, mid, seg_heading)

    def error_at(self, t: np.ndarray) -> np.ndarray:
        """Recorded minus true position at GPS times ``t`` (n,) -> (n, 3) float64 metres."""
        dt = np.asarray(t, np.float64)[:, None] - self.t_start
        err = self.offset_m[None, :] + dt * self.drift_m_per_s[None, :]
        for amp, f, ph in zip(self.jitter_amp_m, self.jitter_freq_hz, self.jitter_phase):
            err += amp[None, :] * np.sin(2.0 * np.pi * f * dt + ph[None, :])
        return err

    def sample(self, step_m: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Poses every ``step_m`` metres -> (times (n,), xyz (n, 3), heading (n,))."""
        n = max(2, int(np.ceil(self.length_m / step_m)) + 1)
        t = np.linspace(self.t_start, self.t_end, n)
        xyz, heading = self.pose_at(t)
        return t, xyz, heading


def offset_polyline(line: np.ndarray, offset_m: float) -> np.ndarray:
    """Shift a polyline ``offset_m`` to the right of its direction (mitred corners).

    line: (k, 2) float64, k >= 2, consecutive vertices distinct -> (k, 2) float64.
    Example: [[0, 0], [10, 0]] offset 2 -> [[0, -2], [10, -2]].
    """
    d = np.diff(line, axis=0)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    right = np.stack([d[:, 1], -d[:, 0]], axis=1)
    vr = np.concatenate([right[:1], right[:-1] + right[1:], right[-1:]])
    vr /= np.maximum(np.linalg.norm(vr, axis=1, keepdims=True), 1e-12)
    seg_r = np.concatenate([right[:1], right])  # the segment normal each vertex miter is measured on
    cos = np.maximum(np.sum(vr * seg_r, axis=1), 1.0 / 3.0)  # miter limit 3x
    return line + vr * (offset_m / cos)[:, None]


def round_corners(line: np.ndarray, radius_m: float, arc_step_deg: float = 5.0) -> np.ndarray:
    """Replace each interior vertex of a (k, 2) polyline by a circular arc of ``radius_m``.

    The tangent length is clipped to 45 % of the shorter adjacent segment, so the radius shrinks on
    short segments. Returns (k', 2) float64 starting and ending at the original end points.
    """
    out = [line[0]]
    for i in range(1, len(line) - 1):
        a, p, b = line[i - 1], line[i], line[i + 1]
        u, w = p - a, b - p
        lu, lw = np.linalg.norm(u), np.linalg.norm(w)
        u, w = u / lu, w / lw
        phi = np.arccos(np.clip(u @ w, -1.0, 1.0))
        if phi < 1e-3:
            out.append(p)
            continue
        tan_len = min(radius_m * np.tan(phi / 2.0), 0.45 * min(lu, lw))
        r = tan_len / np.tan(phi / 2.0)
        start = p - u * tan_len
        left = np.array([-u[1], u[0]])
        side = 1.0 if u[0] * w[1] - u[1] * w[0] > 0 else -1.0
        centre = start + side * r * left
        a0 = np.arctan2(*(start - centre)[::-1])
        n = max(2, int(np.ceil(np.degrees(phi) / arc_step_deg)) + 1)
        ang = a0 + side * np.linspace(0.0, phi, n)
        out.extend(centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1))
    out.append(line[-1])
    return np.asarray(out, dtype=np.float64)


def densify(line: np.ndarray, max_step_m: float) -> np.ndarray:
    """Insert vertices so no (k, d) polyline segment is longer than ``max_step_m``; drops duplicates."""
    keep = np.concatenate([[True], np.linalg.norm(np.diff(line, axis=0), axis=1) > 1e-9])
    line = line[keep]
    pieces = []
    for a, b in itertools.pairwise(line):
        n = max(1, int(np.ceil(np.linalg.norm(b - a) / max_step_m)))
        pieces.append(a + (b - a) * (np.arange(n) / n)[:, None])
    pieces.append(line[-1:])
    return np.concatenate(pieces)


def surface_z(xy: np.ndarray, truth: Mesh | None) -> np.ndarray:
    """Height of the lowest truth surface at (x, y): (n, 2) -> (n,) float64; 0 where there is none.

    Cast upwards from 1 km below, so balconies, eaves or trees above the lane are never taken
    for the road.
    """
    if truth is None or truth.n_faces == 0:
        return np.zeros(len(xy))
    from .raycast import SceneCaster  # open3d only when a terrain is given

    caster = SceneCaster(truth, None)
    origins = np.column_stack([xy, np.full(len(xy), -1000.0)])
    hits = caster.cast(origins, np.tile([0.0, 0.0, 1.0], (len(xy), 1)))
    return np.where(np.isfinite(hits.t), hits.t - 1000.0, 0.0)


def _error_model(params: TrajectoryParams, rng: np.random.Generator):
    def unit(n):
        v = rng.normal(size=(n, 3))
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    offset = unit(1)[0] * rng.uniform(*params.pass_offset_m)
    drift = unit(1)[0] * rng.uniform(0.0, params.drift_m_per_s)
    j = params.n_jitter_terms
    freq = 1.0 / rng.uniform(*params.jitter_period_s, size=j)
    # a sum of j sinusoids with amplitude a has per-axis RMS a * sqrt(j / 2)
    amp = np.full((j, 3), params.jitter_m * np.sqrt(2.0 / j)) if j else np.zeros((0, 3))
    phase = rng.uniform(0.0, 2.0 * np.pi, size=(j, 3))
    return offset, drift, amp, freq, phase


def build_trajectories(
    roads: list[np.ndarray],
    params: TrajectoryParams = TrajectoryParams(),
    rng: np.random.Generator | None = None,
    truth: Mesh | None = None,
) -> list[Trajectory]:
    """Passes of the vehicle along every road, in driving (and GPS time) order.

    roads: list of (k, 2) float64 centre-line polylines (metres, mesh frame), as ``Scene.roads``.
    truth: when given, lane z follows the truth surface under it; else z = 0.
    Returns ``len(roads) * n_passes`` trajectories; traj_id counts 0.. over all of them.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    trajs: list[Trajectory] = []
    t0 = params.gps_start_s
    for road_id, road in enumerate(roads):
        road = np.asarray(road, np.float64)[:, :2]
        for pass_id in range(params.n_passes):
            direction = -1 if (params.alternate_direction and pass_id % 2) else 1
            base = road if direction > 0 else road[::-1]
            base = round_corners(densify(base, np.inf), params.corner_radius_m)  # the road's own curve
            lane = densify(offset_polyline(base, params.lane_offset_m), params.max_step_m)
            path = np.column_stack([lane, surface_z(lane, truth)])
            s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(lane, axis=0), axis=1))])
            offset, drift, amp, freq, phase = _error_model(params, rng)
            tr = Trajectory(len(trajs), road_id, pass_id, direction, path, s, params.speed_m_s, t0,
                            offset, drift, amp, freq, phase)
            trajs.append(tr)
            t0 = tr.t_end + params.pass_gap_s
    return trajs
