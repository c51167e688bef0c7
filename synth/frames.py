"""Pure helpers of the synth campus generator: similarity transforms, the true registration, ASPRS classes
of simulated returns, and the independent random streams (``synth.generate`` re-exports them)."""

from __future__ import annotations

import numpy as np

from .scene import FaceClass, OccluderClass

# ASPRS classes for the simulated returns (truth classes -> LAS classification)
_ASPRS_TRUTH = {FaceClass.GROUND: 2, FaceClass.ROAD: 11, FaceClass.WALL: 6, FaceClass.ROOF: 6,
                FaceClass.GLASS: 6, FaceClass.FRAME: 6, FaceClass.BALCONY: 6, FaceClass.EAVE: 6}
_ASPRS_OCC = {OccluderClass.TREE: 5, OccluderClass.CAR: 1, OccluderClass.PEDESTRIAN: 1, OccluderClass.FENCE: 1}


# ----------------------------------------------------------------------------------- pure helpers


def similarity(scale: float, yaw_deg: float, pitch_deg: float, roll_deg: float, t) -> np.ndarray:
    """(4, 4) float64 ``[s R | t]`` with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    y, p, r = np.radians([yaw_deg, pitch_deg, roll_deg])
    rz = np.array([[np.cos(y), -np.sin(y), 0], [np.sin(y), np.cos(y), 0], [0, 0, 1]])
    ry = np.array([[np.cos(p), 0, np.sin(p)], [0, 1, 0], [-np.sin(p), 0, np.cos(p)]])
    rx = np.array([[1, 0, 0], [0, np.cos(r), -np.sin(r)], [0, np.sin(r), np.cos(r)]])
    m = np.eye(4)
    m[:3, :3] = scale * rz @ ry @ rx
    m[:3, 3] = t
    return m


def random_registration(rng: np.random.Generator) -> np.ndarray:
    """The true MLS -> mesh similarity (campus-local metres): yaw up to 3 deg, pitch/roll up to
    0.3 deg, translation up to 2.5 m, scale within +-0.4 %."""
    return similarity(1.0 + rng.uniform(-0.004, 0.004), rng.uniform(-3, 3), rng.uniform(-0.3, 0.3),
                      rng.uniform(-0.3, 0.3), rng.uniform(-2.5, 2.5, 3) * np.array([1, 1, 0.3]))


def apply(m: np.ndarray, xyz: np.ndarray) -> np.ndarray:
    return np.asarray(xyz, np.float64) @ m[:3, :3].T + m[:3, 3]


def asprs_classes(source: np.ndarray, face_class: np.ndarray) -> np.ndarray:
    """(n,) uint8 ASPRS classification from the simulated hit's source (0 truth / 1 occluder) and class."""
    lut_t = np.zeros(256, np.uint8)
    lut_o = np.ones(256, np.uint8)
    for k, v in _ASPRS_TRUTH.items():
        lut_t[int(k)] = v
    for k, v in _ASPRS_OCC.items():
        lut_o[int(k)] = v
    return np.where(source == 0, lut_t[face_class], lut_o[face_class]).astype(np.uint8)


def streams(seed: int, n: int) -> list[np.random.Generator]:
    """Independent generators per component, so changing one stage's draws leaves the others alone."""
    return [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(n)]
