"""What the MLS cloud is registered against: area-weighted samples of the mesh *surface*, with face normals.

A mesh's vertex set is a poor stand-in for its surface: its density follows the tessellation. A
coarse building model (LoD2-like, a few hundred large triangles) has vertices only at its corners,
tens of metres apart, so an MLS point on a wall finds no vertex near it. Samples of the surface at
a fixed spacing (:func:`mesh_registration_target`) give the same target for any tessellation of the
same surface; each carries the exact normal of its face.

Frames: vertices and samples are float64 campus-local metres; faces are (m, 3) int64 vertex indices.

    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
    >>> xyz, normals = mesh_registration_target(v, np.array([[0, 1, 2], [0, 2, 3]]), spacing_m=0.5)
    >>> len(xyz), float(np.abs(normals[:, 2]).min()), bool(((xyz >= 0) & (xyz <= 4)).all())
    (64, 1.0, True)
"""

from __future__ import annotations

import numpy as np

from storage.errors import InputError
from tasks.geometry.sampling import budget_sample_counts, sample_faces

TARGET_SPACING_M = 0.1  # surface sample spacing: about the vertex spacing of a photogrammetric mesh
TARGET_MAX_POINTS = 3_000_000  # sample budget for the faces near the MLS cloud


def mesh_arrays(vertices: np.ndarray, faces: np.ndarray, name: str = "mesh") -> tuple[np.ndarray, np.ndarray]:
    """Validated (vertices (n, 3) float64, faces (k, 3) int64): faces using a NaN/inf vertex are dropped.

    Raises InputError naming ``name`` for wrong shapes, face indices out of range, or no face left.
    """
    v, f = np.asarray(vertices), np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(None, f"{name} vertices must be an (n, 3) array of metres, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and f.dtype.kind not in "iu"):
        raise InputError(None, f"{name} faces must be an (m, 3) integer array, got {f.dtype} {f.shape}")
    f = f.astype(np.int64, copy=False)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(None, f"{name} face indices lie outside 0..{len(v) - 1}")
    finite = np.isfinite(v).all(axis=1)
    if not finite.all():
        f = f[finite[f].all(axis=1)]
    if len(f) == 0:
        raise InputError(
            None, f"{name} has no faces with finite vertices ({int((~finite).sum())} of {len(v)} are NaN/inf)"
        )
    return v.astype(np.float64, copy=False), f


def faces_in_box(vertices: np.ndarray, faces: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Indices (k,) int64 of the faces whose bounding box meets the box [lo, hi] ((2,) x/y or (3,) metres)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    d = len(lo)
    corners = [vertices[faces[:, q], :d] for q in range(3)]
    meets = (np.minimum.reduce(corners) <= hi) & (np.maximum.reduce(corners) >= lo)
    return np.flatnonzero(meets.all(axis=1))


def used_bounds(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi): (3,) float64 corners of the bounding box of the vertices that ``faces`` use."""
    used = np.zeros(len(vertices), bool)
    used[faces.ravel()] = True
    v = vertices[used]
    return v.min(axis=0), v.max(axis=0)


def mesh_registration_target(
    vertices: np.ndarray,
    faces: np.ndarray,
    spacing_m: float = TARGET_SPACING_M,
    max_samples: int = TARGET_MAX_POINTS,
    rng: np.random.Generator | int | None = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted samples of a mesh surface and their face normals: the registration target.

    vertices: (n, 3) float64 metres; faces: (m, 3) int64. About one sample per ``spacing_m``² of
    surface, at most ``max_samples`` (``tasks.geometry.sampling.budget_sample_counts``: every face of
    positive area gets a sample while the budget allows, otherwise samples are area-proportional).
    The samples are stratified on each face and deterministic for a seed (``rng``: int, Generator or
    None). Degenerate faces get none.

    Returns (xyz (k, 3) float64, normals (k, 3) float64): sample positions in the input frame and
    the unit normal of the face each lies on (sign from the face winding).
    """
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if not spacing_m > 0:
        raise ValueError(f"spacing_m must be positive, got {spacing_m}")
    a = v[f[:, 0]]
    cross = np.cross(v[f[:, 1]] - a, v[f[:, 2]] - a)
    norm = np.linalg.norm(cross, axis=1)
    counts = budget_sample_counts(0.5 * norm, 1.0 / spacing_m**2, int(max_samples), rng)
    xyz, face_idx = sample_faces(v, f, counts, rng)
    return xyz, cross[face_idx] / norm[face_idx, None]  # sampled faces have positive area


__all__ = [
    "TARGET_MAX_POINTS",
    "TARGET_SPACING_M",
    "faces_in_box",
    "mesh_arrays",
    "mesh_registration_target",
    "used_bounds",
]
