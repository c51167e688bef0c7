"""The scan stage's mesh surface samples, which registration aligns the MLS clouds to:
``scan/{source:08x}.npz`` per readable mesh file.

Each file holds ``corner`` (3,) float64 world metres (the mesh's minimum corner), ``xyz`` (k, 3) float32
offsets from it (0.1 mm within 2 km) and ``normals`` (k, 3) float32 unit face normals.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.atomic import atomic_path
from storage.workdir.layout import WorkDir


def samples_path(wd: WorkDir, source: int) -> Path:
    """Where the surface samples of input ``source`` (stable source id) live."""
    return wd.root / "scan" / f"{source:08x}.npz"


def write_surface_samples(path: Path, xyz: np.ndarray, normals: np.ndarray, corner: np.ndarray) -> None:
    """Write samples atomically. xyz: (k, 3) float64 world metres; normals: (k, 3); corner: (3,) float64."""
    corner = np.asarray(corner, np.float64)
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, corner=corner, xyz=(xyz - corner).astype(np.float32), normals=normals)


def read_surface_samples(path: Path, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (k, 3) float64 metres relative to ``origin`` (3,) float64 world, normals (k, 3) float64)."""
    with np.load(path) as z:
        return z["xyz"].astype(np.float64) + (z["corner"] - origin), z["normals"].astype(np.float64)
