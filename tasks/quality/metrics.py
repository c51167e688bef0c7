"""Measured accuracy of a mesh against the truth mesh: accuracy, completeness, Chamfer, F-score, holes.

Both surfaces are sampled (area-weighted, stratified, deterministic: :mod:`tasks.geometry.sampling`) and
each sample's exact unsigned distance to the other mesh is measured (:mod:`tasks.geometry.distance`:
open3d's ``RaycastingScene`` in float32 around the data, refined in float64 on the face it returns).
Everything is accumulated as mergeable sums (:mod:`tasks.quality.stats`), so results of chunks and tiles
(:mod:`tasks.quality.tiled`) merge exactly:

- accuracy: pred -> truth distances; precision(tau) = pred area within tau of the truth;
- completeness: truth -> pred distances; recall(tau) = truth area within tau of the prediction;
- uncovered area (holes): truth area (restricted to ``true_face_mask``, e.g. facades) where no
  predicted surface crosses the segment of +- ``hole_threshold_m`` along the truth normal; also the
  truth area farther than ``hole_threshold_m`` from the prediction (an eroded measure of holes).

    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [4, 0, 0], [4, 4, 0], [0, 4, 0]], float)
    >>> f = np.array([[0, 1, 2], [0, 2, 3]])
    >>> r = evaluate_mesh(v + [0, 0, 0.03], f, v, f, spacing_m=0.1)
    >>> round(r.accuracy.mean_m, 4), r.fscore
    (0.03, (1.0, 1.0))
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from storage.errors import InputError
from storage.ids import TileId
from tasks.geometry.distance import MeshDistance, point_to_mesh_distance, unit_face_normals
from tasks.geometry.sampling import (
    faces_in_boxes,
    iter_surface_samples,
    sample_boxes,
    samples_inside,
    seed_of,
)
from tasks.quality.stats import QualityPartial, QualityReport, SideSums

# point_to_mesh_distance: still imported from here by tests/synth/test_generate.py (to move to
# tasks.geometry.distance, then drop it from this import and __all__).
__all__ = ["FACADE_CLASS_IDS", "class_names_of", "evaluate_mesh", "evaluate_partial", "facade_mask",
           "point_to_mesh_distance", "validated_mesh"]

# synth.scene.FaceClass values of facade faces: WALL, GLASS, FRAME, BALCONY, EAVE.
FACADE_CLASS_IDS = (2, 4, 5, 6, 7)


def validated_mesh(vertices, faces, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3) float64, faces (m, 3) int64) of a mesh, or InputError naming ``name`` and the problem."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or (f.size and f.shape[1] != 3):
        raise InputError(None, f"{name} mesh: vertices must be (n, 3) and faces (m, 3), "
                               f"not {v.shape} and {f.shape}")
    if not np.isfinite(v).all():
        bad = int((~np.isfinite(v).all(1)).sum())
        raise InputError(None, f"{name} mesh: {bad} vertices are NaN or infinite")
    f = f.reshape(-1, 3).astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(None, f"{name} mesh: face indices outside 0..{len(v) - 1}")
    return v, f


def class_names_of(true_face_class, class_names) -> tuple[str, ...]:
    """Names of classes 0..c: from a list or {id: name} (missing ids ``class_<id>``), else ``class_<id>``
    up to the largest class in ``true_face_class`` ((m,) int)."""
    if isinstance(class_names, Mapping):
        n = max(class_names, default=-1) + 1
        return tuple(str(class_names.get(c, f"class_{c}")) for c in range(n))
    if class_names is not None:
        return tuple(map(str, class_names))
    if true_face_class is None or len(true_face_class) == 0:
        return ()
    return tuple(f"class_{c}" for c in range(int(np.max(true_face_class)) + 1))


def evaluate_partial(pred_vertices, pred_faces, true_vertices, true_faces, *, taus=(0.05, 0.10),
                     spacing_m: float = 0.02, density_per_m2: float | None = None, true_face_mask=None,
                     true_face_class=None, class_names: Sequence[str] | Mapping[int, str] | None = None,
                     region=None, tile: TileId | None = None, tile_size_m: float = 100.0,
                     hole_threshold_m: float = 0.20, max_distance_m: float | None = None, rng=0,
                     chunk_size: int = 1_000_000, exact: bool = True) -> QualityPartial:
    """The mergeable sums of :func:`evaluate_mesh` for the samples inside ``region`` and ``tile``.

    Samples are drawn on the faces given and kept when they lie in the region / tile; their
    distances are measured to all faces given, so for a tile pass each mesh's faces within the tile
    plus a buffer (see :func:`evaluate_by_tile`). Samples depend only on face geometry and the
    seed, so partials of disjoint tiles add up to the global figures.
    """
    pv, pf = validated_mesh(pred_vertices, pred_faces, "predicted")
    tv, tf = validated_mesh(true_vertices, true_faces, "truth")
    tc = None if true_face_class is None else np.asarray(true_face_class, np.int64)
    mask = np.ones(len(tf), bool) if true_face_mask is None else np.asarray(true_face_mask, bool)
    if len(mask) != len(tf) or (tc is not None and len(tc) != len(tf)):
        raise InputError(None, f"truth face mask/classes must have one entry per truth face ({len(tf)})")
    names, taus = class_names_of(tc, class_names), tuple(float(t) for t in taus)
    density = density_per_m2 if density_per_m2 is not None else 1.0 / spacing_m**2
    seed, cap = seed_of(rng), math.inf if max_distance_m is None else float(max_distance_m)
    boxes = sample_boxes(region, tile, tile_size_m)
    acc, comp = SideSums.empty(1 + len(names), len(taus)), SideSums.empty(1 + len(names), len(taus))
    for side, (sv, sf), (ov, of), salt in ((acc, (pv, pf), (tv, tf), 0), (comp, (tv, tf), (pv, pf), 1)):
        other = MeshDistance(ov, of)
        for pts, fid, w in iter_surface_samples(sv, sf, faces_in_boxes(sv, sf, boxes), density, seed ^ salt, chunk_size):
            keep = samples_inside(pts, boxes, tile, tile_size_m)
            pts, fid, w = pts[keep], fid[keep], w[keep]
            d, ofid = other.query(pts, exact)
            cls, ok = np.full(len(d), -1), (ofid >= 0) if side is acc else np.ones(len(d), bool)
            if tc is not None:  # pred samples take the class of their nearest truth face
                cls[ok] = tc[ofid[ok]] if side is acc else tc[fid]
                cls[cls >= len(names)] = -1  # classes without a name count in the totals only
            if side is acc:
                in_mask = holes = np.zeros(len(d), bool)
            else:
                in_mask = mask[fid]
                holes = ~other.covered_along(pts, unit_face_normals(sv, sf[fid]), hole_threshold_m)
            side.add(np.minimum(d, cap), w, cls, in_mask, holes, taus, hole_threshold_m)
        del other
    spacing = spacing_m if density_per_m2 is None else 1.0 / math.sqrt(density_per_m2)
    return QualityPartial(acc, comp, taus, float(hole_threshold_m), float(spacing),
                          max_distance_m, names)


def evaluate_mesh(pred_vertices, pred_faces, true_vertices, true_faces, **kwargs) -> QualityReport:
    """Accuracy, completeness, Chamfer, F-score at each tau and uncovered (hole) area of a mesh.

    pred_*/true_*: vertices (n, 3) float64 metres and faces (m, 3) int64, in the same frame (world
    coordinates are fine). Keyword arguments (see :func:`evaluate_partial`): taus (metres, default
    (0.05, 0.10)); spacing_m of the surface samples (0.02) or density_per_m2; true_face_mask
    ((m,) bool, e.g. facade faces: the area over which holes are measured; default all);
    true_face_class ((m,) int) and class_names for per-class figures; region (xmin, ymin, xmax, ymax)
    or a 3D box, half-open; hole_threshold_m (0.20); max_distance_m to cap distances (None); rng.
    """
    return evaluate_partial(pred_vertices, pred_faces, true_vertices, true_faces, **kwargs).report()


def facade_mask(true_face_class: np.ndarray) -> np.ndarray:
    """(m,) bool: faces of a facade class (synth.scene.FaceClass WALL, GLASS, FRAME, BALCONY, EAVE)."""
    return np.isin(np.asarray(true_face_class), FACADE_CLASS_IDS)

