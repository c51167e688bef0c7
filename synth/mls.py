"""Simulated mobile laser scanning: rotating laser heads on a vehicle, ray cast against the scene.

Scanner model (one model, two presets). A head spins at ``profile_rate_hz`` about its spin axis
``a`` (vehicle frame: x forward, y left, z up) and fires ``pulses_per_profile`` pulses per turn on
each of its channels; channel c's beam is ``cos(phi_c) (cos(theta) u + sin(theta) w) +
sin(phi_c) a`` with (u, w, a) orthonormal and theta the rotation angle.

- :meth:`MlsParams.vmx450` (the default; RIEGL VMX-450-like, the paper's system): two
  single-channel heads 2.5 m above the road, each spinning a full 360 deg profile in a vertical plane
  yawed +-35 deg from the cross-track plane (the "X" / butterfly pattern: every facade is seen
  once looking forward and once looking back). On a wall parallel to the track at distance d the
  density of one pass is ``2 * PRR_head * cos(35 deg) * cos^2(elevation) / (2 pi v d)``; with
  250 profiles/s x 5,600 pulses and v = 9 m/s that is ~4,000 pts/m^2 at 10 m (the paper's
  figure; a real VQ-450 fires 550 kHz, so this is ~2.5x a real head, or a real head at ~4 m/s).
- :meth:`MlsParams.spinner32`: one 32-channel spinner (Velodyne HDL-32E-like: 10 Hz, channels
  -30.67 to +10.67 deg), upright on the roof; it never sees above ~+10.67 deg.

All pulses of all heads are interleaved in one time line (pulse k at ``t_start + k / PRR_total``),
so points come out in GPS-time order. Range noise is Gaussian along the ray (sigma 5 mm), plus a
constant per-channel range bias (the two VMX heads: +-10 mm); the trajectory error of
:mod:`synth.trajectory` (per-pass offset + drift + low-frequency wander) is added to every point, as
georeferencing with a wrong pose would. Returns beyond ``max_range_m`` (after noise) and closer than
``min_range_m`` are dropped; glass returns only with ``glass_return_prob``. Single returns only.
Everything is in the mesh frame (campus-local metres, float64, z up).

Measured with :func:`synth.realism.mls_wall_stats` on a street of 10 m tall walls 3-16 m from the
lane (default preset, two passes): wall density p50 7,200 / 4,800 / 2,550 pts/m^2 at 0-5 / 5-10 /
10-20 m (x ``density_scale``; 0.15 gives 1,080 / 730 / 385 against real street MLS 2,500 / 700 /
370); flat-wall noise 3.7 mm within one rotation (the 5 mm along the ray, seen obliquely) and
12 mm over one pass; pass-to-pass offset median 24 mm.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, fields, replace

import numpy as np

from .raycast import SOURCE_OCCLUDER, SOURCE_TRUTH, SceneCaster
from .scene import FaceClass, OccluderClass, Scene
from .trajectory import Trajectory

# Diffuse reflectance at the laser wavelength (~1550 nm), by class; drives intensity.
TRUTH_REFLECTANCE = {
    FaceClass.GROUND: 0.45, FaceClass.ROAD: 0.20, FaceClass.WALL: 0.60, FaceClass.ROOF: 0.35,
    FaceClass.GLASS: 0.08, FaceClass.FRAME: 0.75, FaceClass.BALCONY: 0.55, FaceClass.EAVE: 0.40,
}
OCCLUDER_REFLECTANCE = {
    OccluderClass.TREE: 0.45, OccluderClass.CAR: 0.30, OccluderClass.PEDESTRIAN: 0.30,
    OccluderClass.FENCE: 0.50,
}


@dataclass(frozen=True)
class ScannerHead:
    """One laser head. position_m: vehicle frame metres above the road reference point;
    spin_axis: vehicle frame (normalised here); channel_elev_deg: beam angles out of the spin plane;
    range_bias_m: per-channel constant range error (a calibration residual; makes heads and
    channels disagree by a few mm, as in real multi-head / multi-channel data)."""

    position_m: tuple[float, float, float]
    spin_axis: tuple[float, float, float]
    channel_elev_deg: tuple[float, ...] = (0.0,)
    phase_deg: float = 0.0
    range_bias_m: tuple[float, ...] | None = None  # per channel calibration residual; None = 0

    def basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(u, w, a): (3,) float64 unit vectors, vehicle frame; theta = 0 fires along u."""
        a = np.asarray(self.spin_axis, np.float64)
        a = a / np.linalg.norm(a)
        u = np.cross([0.0, 0.0, 1.0], a)
        u = np.array([1.0, 0.0, 0.0]) if np.linalg.norm(u) < 1e-9 else u / np.linalg.norm(u)
        return u, np.cross(a, u), a


def _profile_heads(yaw_deg: float, height_m: float, bias_m: float) -> tuple[ScannerHead, ...]:
    return tuple(
        ScannerHead(position_m=(-0.5, 0.3 * sgn, height_m),
                    spin_axis=(np.cos(np.radians(sgn * yaw_deg)), np.sin(np.radians(sgn * yaw_deg)), 0.0),
                    phase_deg=90.0 * (sgn < 0), range_bias_m=(sgn * bias_m,))
        for sgn in (1, -1)
    )


@dataclass(frozen=True)
class MlsParams:
    """Scanner configuration. The rates are per head and per channel, before ``density_scale``."""

    heads: tuple[ScannerHead, ...] = _profile_heads(35.0, 2.5, 0.010)
    profile_rate_hz: float = 250.0  # turns per second (VQ-450: up to 200)
    pulses_per_profile: int = 5_600  # per channel per turn (0.064 deg steps)
    density_scale: float = 1.0  # multiplies point density: rate and pulses each by sqrt(scale)
    max_range_m: float = 120.0
    min_range_m: float = 1.0
    range_noise_m: float = 0.005  # 1 sigma, along the ray
    glass_return_prob: float = 0.5
    intensity_ref_range_m: float = 30.0  # intensity halves at this range
    apply_trajectory_error: bool = True
    max_rays_per_chunk: int = 2_000_000
    nthreads: int = 0  # open3d threads; 0 = all cores

    @classmethod
    def vmx450(cls, yaw_deg: float = 35.0, height_m: float = 2.5, head_bias_m: float = 0.010,
               **kw) -> MlsParams:
        """Two profile heads yawed +-``yaw_deg``, ``height_m`` above the road, with range biases
        +-``head_bias_m``; ~4,000 pts/m^2 at 10 m and 9 m/s. ``MlsParams()`` is this preset."""
        return cls(heads=_profile_heads(yaw_deg, height_m, head_bias_m), **kw)

    @classmethod
    def spinner32(cls, **kw) -> MlsParams:
        """One upright 32-channel spinner at 2.3 m (HDL-32E-like: 10 Hz, 1,800 pulses per channel)."""
        bias = np.random.default_rng(32).normal(0.0, 0.006, 32)  # fixed per-laser calibration residual
        head = ScannerHead(position_m=(0.0, 0.0, 2.3), spin_axis=(0.0, 0.0, 1.0),
                           channel_elev_deg=tuple(np.round(np.linspace(-30.67, 10.67, 32), 3)),
                           range_bias_m=tuple(np.round(bias, 4)))
        base = {"heads": (head,), "profile_rate_hz": 10.0, "pulses_per_profile": 1_800, "max_range_m": 100.0}
        return cls(**{**base, **kw})

    def scaled(self) -> tuple[float, int]:
        """(profile rate Hz, pulses per profile) after ``density_scale``."""
        k = np.sqrt(self.density_scale)
        return self.profile_rate_hz * k, max(1, round(self.pulses_per_profile * k))

    @property
    def n_channels(self) -> int:
        return len(self.heads[0].channel_elev_deg)

    @property
    def pulse_rate_hz(self) -> float:
        """Pulses per second, all heads and channels together."""
        f, n = self.scaled()
        return f * n * self.n_channels * len(self.heads)

    def __post_init__(self):
        if not self.heads or len({len(h.channel_elev_deg) for h in self.heads}) != 1:
            raise ValueError("MlsParams.heads: need >= 1 head, all with the same number of channels")
        if any(h.range_bias_m is not None and len(h.range_bias_m) != len(h.channel_elev_deg) for h in self.heads):
            raise ValueError("MlsParams.heads: range_bias_m needs one value per channel")
        if not (self.density_scale > 0 and self.profile_rate_hz > 0 and self.pulses_per_profile > 0):
            raise ValueError("MlsParams: density_scale, profile_rate_hz, pulses_per_profile must be > 0")
        if not 0 <= self.min_range_m < self.max_range_m:
            raise ValueError("MlsParams: need 0 <= min_range_m < max_range_m")


@dataclass
class MlsChunk:
    """A time-ordered block of simulated returns (n points) from ``n_rays`` pulses.

    xyz: (n, 3) float64 mesh-frame metres (trajectory error and noise included);
    gps_time: (n,) float64 seconds of GPS week, non-decreasing; intensity: (n,) uint16;
    rgb: (n, 3) uint16 (face colour x 257); source: (n,) uint8 0 truth / 1 occluder;
    face: (n,) int64 face index in its source mesh; face_class: (n,) uint8 FaceClass or
    OccluderClass (by source); traj_id: (n,) uint16 (LAS point_source_id); pass_id: (n,) uint8
    pass of its road; scanner_id: (n,) uint8 head; profile_id: (n,) uint32 turn of the head within
    the trajectory; scan_angle_deg: (n,) float32 head rotation angle in [-180, 180);
    range_m: (n,) float32 measured range; return_number, n_returns: (n,) uint8 (single return: 1, 1).
    """

    xyz: np.ndarray
    gps_time: np.ndarray
    intensity: np.ndarray
    rgb: np.ndarray
    source: np.ndarray
    face: np.ndarray
    face_class: np.ndarray
    traj_id: np.ndarray
    pass_id: np.ndarray
    scanner_id: np.ndarray
    profile_id: np.ndarray
    scan_angle_deg: np.ndarray
    range_m: np.ndarray
    return_number: np.ndarray
    n_returns: np.ndarray
    n_rays: int = 0

    def __len__(self) -> int:
        return len(self.gps_time)

    @staticmethod
    def concat(chunks: list[MlsChunk]) -> MlsChunk:
        """All chunks' points in order; n_rays summed. Needs at least one chunk."""
        names = [f.name for f in fields(MlsChunk) if f.name != "n_rays"]
        arrays = {k: np.concatenate([getattr(c, k) for c in chunks]) for k in names}
        return MlsChunk(**arrays, n_rays=sum(c.n_rays for c in chunks))


def _reflectance_lut() -> list[np.ndarray]:
    out = []
    for table in (TRUTH_REFLECTANCE, OCCLUDER_REFLECTANCE):
        lut = np.full(256, 0.4)
        for k, v in table.items():
            lut[int(k)] = v
        out.append(lut)
    return out


def _beam_table(params: MlsParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For pulse k at row ``k % P``: vehicle-frame beam (P, 3) float64, rotation angle theta (P,)
    radians and range bias (P,) metres.

    The firing pattern repeats every P = heads x channels x pulses_per_profile pulses: pulse k is
    head ``k % H``, then channel ``(k // H) % C``, then step ``k // (H C)`` of the turn.
    """
    _, n_pp = params.scaled()
    n_heads, n_ch = len(params.heads), params.n_channels
    k = np.arange(n_heads * n_ch * n_pp)
    head, ch, step = k % n_heads, (k // n_heads) % n_ch, k // (n_heads * n_ch)
    phase = np.radians([h.phase_deg for h in params.heads])
    theta = 2.0 * np.pi * step / n_pp + phase[head]
    basis = np.array([np.stack(h.basis()) for h in params.heads])  # (heads, 3 [u, w, a], 3)
    elev = np.radians(np.array([h.channel_elev_deg for h in params.heads]))[head, ch]
    ce = np.cos(elev)[:, None]
    beam = ce * (np.cos(theta)[:, None] * basis[head, 0] + np.sin(theta)[:, None] * basis[head, 1])
    beam += np.sin(elev)[:, None] * basis[head, 2]
    bias = np.array([h.range_bias_m or (0.0,) * n_ch for h in params.heads], np.float64)[head, ch]
    return beam, theta, bias


def _rays(traj: Trajectory, params: MlsParams, k: np.ndarray, beam: np.ndarray, origin_m: np.ndarray):
    """Pulse indices k (n,) int64 of one trajectory (k[0] a multiple of the head count) ->
    (t (n,) float64 GPS s, rays (n, 6) float32: origin relative to ``origin_m``, unit direction).

    float32 keeps the per-ray work light: relative origins within 2 km resolve 0.1 mm, directions
    1e-7 rad (10 um at 100 m), far below the 5 mm range noise.
    """
    t = traj.t_start + k / params.pulse_rate_hz
    pos, heading = traj.pose_at(t)
    c, s = np.cos(heading).astype(np.float32), np.sin(heading).astype(np.float32)
    rays = np.empty((len(k), 6), np.float32)
    rays[:, :3] = pos - origin_m
    n_heads = len(params.heads)
    for h, head in enumerate(params.heads):
        mx, my, mz = head.position_m
        ch, sh = c[h::n_heads], s[h::n_heads]
        rays[h::n_heads, 0] += mx * ch - my * sh
        rays[h::n_heads, 1] += mx * sh + my * ch
        rays[h::n_heads, 2] += mz
    b = beam[k % len(beam)]
    rays[:, 3] = b[:, 0] * c - b[:, 1] * s
    rays[:, 4] = b[:, 0] * s + b[:, 1] * c
    rays[:, 5] = b[:, 2]
    return t, rays


def simulate_mls(
    scene: Scene,
    trajectories: list[Trajectory],
    params: MlsParams = MlsParams(),
    rng: np.random.Generator | None = None,
) -> Iterator[MlsChunk]:
    """Scan ``scene`` (truth + occluders) from each trajectory in turn; yield time-ordered chunks.

    Each chunk covers at most ``params.max_rays_per_chunk`` pulses of one trajectory (so memory is
    bounded; a chunk may hold 0 points, but still reports its ``n_rays``). Trajectories should be
    in GPS-time order (as ``build_trajectories`` returns them) for the stream to be time-ordered.
    Same ``rng`` seed, scene, trajectories and params -> identical arrays.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    caster = SceneCaster(scene.truth, scene.occluders.mesh if scene.occluders else None)
    refl = _reflectance_lut()
    rate = params.pulse_rate_hz
    table = _beam_table(params)
    block = len(params.heads) * params.n_channels
    per_chunk = max(block, params.max_rays_per_chunk // block * block)
    for traj in trajectories:
        n_total = int(np.floor(traj.duration_s * rate))
        for k0 in range(0, n_total, per_chunk):
            k = np.arange(k0, min(n_total, k0 + per_chunk), dtype=np.int64)
            yield _scan_block(traj, params, k, caster, refl, table, rng)


def _smooth_error(traj: Trajectory, t: np.ndarray, step_s: float = 0.01) -> np.ndarray:
    """traj.error_at on sorted times t (n,), linearly interpolated from a ``step_s`` grid.

    The error's shortest period is ~1 s, so a 10 ms grid is exact to well under 0.01 mm.
    """
    grid = np.arange(t[0], t[-1] + step_s, step_s)
    e = traj.error_at(grid)
    return np.stack([np.interp(t, grid, e[:, i]) for i in range(3)], axis=1)


def _scan_block(traj, params, k, caster, refl, table, rng) -> MlsChunk:
    t, rays = _rays(traj, params, k, table[0].astype(np.float32), caster.origin_m)
    hits = caster.cast_local(rays, params.nthreads)
    keep = np.flatnonzero(np.isfinite(hits.t) & (hits.t >= params.min_range_m))
    source, face = hits.source[keep], hits.face[keep]
    row = caster.global_face(source, face)
    cls = caster.all_face_class[row]
    glass = (source == SOURCE_TRUTH) & (cls == FaceClass.GLASS)
    drop = glass & (rng.random(len(keep)) >= params.glass_return_prob)
    bias = table[2][k[keep] % len(table[2])]
    rng_m = hits.t[keep] + bias + rng.normal(0.0, params.range_noise_m, len(keep))
    ok = ~drop & (rng_m <= params.max_range_m) & (rng_m >= params.min_range_m)
    keep, source, face, row, cls, rng_m = keep[ok], source[ok], face[ok], row[ok], cls[ok], rng_m[ok]

    d = rays[keep, 3:].astype(np.float64)
    xyz = rays[keep, :3] + d * rng_m[:, None] + caster.origin_m
    if params.apply_trajectory_error and len(keep):
        xyz += _smooth_error(traj, t[keep])
    normal = caster.all_face_normal[row]
    cos_inc = np.abs(np.sum(normal * d, axis=1))
    r_lut = np.where(source == SOURCE_OCCLUDER, refl[1][cls], refl[0][cls])
    falloff = 1.0 / (1.0 + (rng_m / params.intensity_ref_range_m) ** 2)
    intensity = np.round(65535.0 * np.clip(r_lut * cos_inc * falloff, 0.0, 1.0)).astype(np.uint16)
    rgb = caster.all_face_color[row].astype(np.uint16) * 257
    n, kk = len(keep), k[keep]
    n_heads, period = len(params.heads), len(table[1])
    return MlsChunk(
        xyz=xyz,
        gps_time=t[keep],
        intensity=intensity,
        rgb=rgb,
        source=source.astype(np.uint8),
        face=face,
        face_class=cls,
        traj_id=np.full(n, traj.traj_id, np.uint16),
        pass_id=np.full(n, traj.pass_id, np.uint8),
        scanner_id=(kk % n_heads).astype(np.uint8),
        profile_id=(kk // period).astype(np.uint32),
        scan_angle_deg=((np.degrees(table[1][kk % period]) + 180.0) % 360.0 - 180.0).astype(np.float32),
        range_m=rng_m.astype(np.float32),
        return_number=np.ones(n, np.uint8),
        n_returns=np.ones(n, np.uint8),
        n_rays=len(k),
    )


def with_density(params: MlsParams, density_scale: float) -> MlsParams:
    """A copy of ``params`` with another ``density_scale`` (campus presets run lighter)."""
    return replace(params, density_scale=density_scale)
