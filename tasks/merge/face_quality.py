"""The per-face quality a merged tile carries to the viewer: the signed scan-to-model distance of each face
(:func:`tasks.geometry.deviation.face_deviation`, from the tile's MLS points) and the grader's p(bad) of the
patch the face lies in. Pure: arrays in, a :class:`TileMesh` out.

Every MLS point counts, held-out strips too (``tasks.geometry.holdout``): this is what the user's scan says of
the output, not a test of the repair (the quality stage's held-out figures are that). A point whose nearest
surface lies in the next tile is measured to this tile's faces only, and left out when they are farther than
``DEVIATION_MAX_M``: at most a band along the tile's border loses points.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from storage.contracts.tile_mesh import TileMesh
from storage.grid import PatchGrid
from tasks.geometry.deviation import face_deviation

DEVIATION_MAX_M = 0.25  # points farther from the model are not the surface (cars, trees, what the model lacks)
DEVIATION_MAX_POINTS = 2_000_000  # a tile's points beyond this are thinned by a fixed stride (memory, time)


def face_patch_scores(face_patch: np.ndarray, patch_keys: np.ndarray, scores: np.ndarray | None) -> np.ndarray:
    """(m,) float32 score of each face's patch (NaN for a patch without one, or without a score table).

    face_patch: (m,) int64 patch keys; patch_keys: (u,) int64 sorted; scores: (u,) float or None.

    >>> face_patch_scores(np.array([5, 9, 7]), np.array([5, 7]), np.array([0.25, 0.75])).tolist()
    [0.25, nan, 0.75]
    """
    out = np.full(len(face_patch), np.nan, np.float32)
    if scores is None or not len(patch_keys):
        return out
    at = np.clip(np.searchsorted(patch_keys, face_patch), 0, len(patch_keys) - 1)
    hit = patch_keys[at] == face_patch
    out[hit] = np.asarray(scores, np.float32)[at[hit]]
    return out


def with_face_quality(mesh: TileMesh, points: np.ndarray, patch_keys: np.ndarray, scores: np.ndarray | None,
                      grid: PatchGrid, origin, thinned_by: int = 1) -> tuple[TileMesh, dict]:
    """``mesh`` with ``face_deviation`` and ``face_score``, and a summary of them.

    points: (k, 3) float32 campus-local MLS points of the tile (already every ``thinned_by``-th, or all:
    more than ``DEVIATION_MAX_POINTS`` are thinned here by a fixed stride); patch_keys, scores: the tile's patch
    keys (sorted) and their grades' scores (None without grades); grid, origin: the campus grid, (3,) float64
    world.
    """
    v = mesh.vertices.astype(np.float64)
    step = max(1, -(-len(points) // DEVIATION_MAX_POINTS))
    dev, n = face_deviation(np.asarray(points[::step], np.float64), v, mesh.faces, DEVIATION_MAX_M)
    tri = mesh.vertices[mesh.faces] if mesh.n_faces else np.zeros((0, 3, 3), np.float32)
    face_patch = grid.pack(grid.face_cells([tri[:, c, a] for c in range(3) for a in range(3)], origin)) \
        if mesh.n_faces else np.zeros(0, np.int64)
    score = face_patch_scores(face_patch, patch_keys, scores)
    seen = np.isfinite(dev)
    stats = {"deviation_faces": int(seen.sum()), "deviation_points": int(n.sum()), "deviation_stride": step * thinned_by,
             "deviation_p50_m": float(np.median(np.abs(dev[seen]))) if seen.any() else None}
    return replace(mesh, face_deviation=dev, face_score=score), stats


__all__ = ["DEVIATION_MAX_M", "face_patch_scores", "with_face_quality"]
