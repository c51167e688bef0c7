"""Measured accuracy of a mesh against the truth mesh: accuracy, completeness, Chamfer, F-score, holes.

Both surfaces are sampled (area-weighted, stratified, deterministic: :mod:`tasks.geometry.sampling`) and
each sample's exact unsigned distance to the other mesh is measured (:mod:`tasks.geometry.distance`:
open3d's ``RaycastingScene`` in float32 around the data, refined in float64 on the face it returns). Everything is accumulated as
area-weighted sums plus a fine distance histogram, so results of chunks and tiles merge exactly
(sums of areas and counts, never averages of averages):

- accuracy: pred -> truth distances; precision(tau) = pred area within tau of the truth;
- completeness: truth -> pred distances; recall(tau) = truth area within tau of the prediction;
- uncovered area (holes): truth area (restricted to ``true_face_mask``, e.g. facades) where no
  predicted surface crosses the segment of +- ``hole_threshold_m`` along the truth normal; also the
  truth area farther than ``hole_threshold_m`` from the prediction (an eroded measure of holes).

Percentiles come from the histogram (0.05 mm bins below 0.5 m, 0.1 % relative above): the value
reported is the weighted mean distance of the bin that holds the quantile.

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
from dataclasses import dataclass, field, replace

import numpy as np

from storage.errors import InputError
from storage.ids import TileId
from tasks.geometry.distance import (
    MeshDistance,
    closest_points_on_triangles,
    point_to_mesh_distance,
    unit_face_normals,
)
from tasks.geometry.sampling import (
    face_areas,
    faces_in_boxes,
    iter_surface_samples,
    sample_boxes,
    sample_counts,
    sample_surface,
    sample_weights,
    samples_inside,
    seed_of,
)

# synth.scene.FaceClass values of facade faces: WALL, GLASS, FRAME, BALCONY, EAVE.
FACADE_CLASS_IDS = (2, 4, 5, 6, 7)

_FINE_STEP, _FINE_MAX, _N_FINE = 5e-5, 0.5, 10_000
_RATIO, _N_COARSE = 1.001, 12_208  # 0.5 m .. 100 km, then one overflow bin
_N_BINS = _N_FINE + _N_COARSE + 1


# ----------------------------------------------------------------------------- accumulated statistics

def _bins(d: np.ndarray) -> np.ndarray:
    """Histogram bin of each distance: (k,) float64 m -> (k,) int64 in [0, _N_BINS)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        coarse = _N_FINE + np.floor(np.log(np.maximum(d, _FINE_MAX) / _FINE_MAX) / math.log(_RATIO))
    b = np.where(d < _FINE_MAX, np.floor(d / _FINE_STEP), coarse)
    return np.minimum(b, _N_BINS - 1).astype(np.int64)


@dataclass
class _Side:
    """Area-weighted sums of one direction's distances, per group (row 0: all; row 1 + c: class c).

    All fields are sums (or a max), so two _Side values of disjoint samples merge exactly.
    """

    n: np.ndarray  # (G,) samples
    w: np.ndarray  # (G,) m²
    wd: np.ndarray  # (G,) m³  (sum of area x distance)
    wd2: np.ndarray  # (G,) m⁴
    dmax: np.ndarray  # (G,) m
    within: np.ndarray  # (G, T) m² within each tau
    masked: np.ndarray  # (G,) m² of samples under the face mask
    far: np.ndarray  # (G, 2) m² beyond the hole threshold: all, under the mask
    holes: np.ndarray  # (G, 2) m² not covered along the normal: all, under the mask
    hist_w: np.ndarray  # (G, B) m² per distance bin
    hist_wd: np.ndarray  # (G, B) m³ per distance bin

    @classmethod
    def empty(cls, groups: int, n_taus: int) -> _Side:
        z = lambda *s: np.zeros(s)
        return cls(np.zeros(groups, np.int64), z(groups), z(groups), z(groups), z(groups), z(groups, n_taus),
                   z(groups), z(groups, 2), z(groups, 2), z(groups, _N_BINS), z(groups, _N_BINS))

    def add(self, d, w, cls, masked, holes, taus, hole_m) -> None:
        """d, w: (k,) float64 m, m²; cls: (k,) int64 class (-1: none); masked, holes: (k,) bool."""
        has = cls >= 0
        g = np.concatenate([np.zeros(len(d), np.int64), 1 + cls[has]])
        d, w, masked, holes = (np.concatenate([x, x[has]]) for x in (d, w, masked, holes))
        G = len(self.n)
        s = lambda x: np.bincount(g, x, minlength=G)
        wd = w * d
        self.n += np.bincount(g, minlength=G)
        self.w += s(w)
        self.wd += s(wd)
        self.wd2 += s(wd * d)
        np.maximum.at(self.dmax, g, d)
        for t, tau in enumerate(taus):
            self.within[:, t] += s(w * (d <= tau))
        self.masked += s(w * masked)
        for i, flag in enumerate((d > hole_m, holes)):
            into = self.far if i == 0 else self.holes
            into[:, 0] += s(w * flag)
            into[:, 1] += s(w * (flag & masked))
        flat = g * _N_BINS + _bins(d)
        self.hist_w += np.bincount(flat, w, minlength=G * _N_BINS).reshape(G, _N_BINS)
        self.hist_wd += np.bincount(flat, wd, minlength=G * _N_BINS).reshape(G, _N_BINS)

    def __add__(self, other: _Side) -> _Side:
        return _Side(**{k: (np.maximum if k == "dmax" else np.add)(v, getattr(other, k))
                        for k, v in vars(self).items()})

    def quantile(self, g: int, q: float) -> float:
        cum = np.cumsum(self.hist_w[g])
        if cum[-1] <= 0:
            return math.nan
        k = min(int(np.searchsorted(cum, q * cum[-1])), _N_BINS - 1)
        return float(self.hist_wd[g, k] / self.hist_w[g, k])

    def stats(self, g: int) -> DistanceStats:
        w = self.w[g]
        div = (lambda x: float(x / w)) if w > 0 else (lambda x: math.nan)
        return DistanceStats(
            n_samples=int(self.n[g]), area_m2=float(w), mean_m=div(self.wd[g]),
            median_m=self.quantile(g, 0.5), p90_m=self.quantile(g, 0.9), p95_m=self.quantile(g, 0.95),
            rms_m=math.sqrt(div(self.wd2[g])), max_m=float(self.dmax[g]) if w > 0 else math.nan,
            within=tuple(div(x) for x in self.within[g]),
        )


@dataclass(frozen=True)
class DistanceStats:
    """Area-weighted statistics of one direction's distances (metres); within[i]: area fraction <= taus[i]."""

    n_samples: int
    area_m2: float
    mean_m: float
    median_m: float
    p90_m: float
    p95_m: float
    rms_m: float
    max_m: float
    within: tuple[float, ...]


def _fscore(p: float, r: float) -> float:
    if math.isnan(p) or math.isnan(r):
        return math.nan
    return 0.0 if p + r == 0 else 2 * p * r / (p + r)


def _jsonable(x):
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, (tuple, list)):
        return [_jsonable(v) for v in x]
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    return x


@dataclass(frozen=True)
class QualityReport:
    """Measured quality of a predicted mesh against the truth (metres, m², fractions in [0, 1]).

    accuracy: pred -> truth; completeness: truth -> pred. chamfer_m: mean of the two mean distances;
    chamfer_l2_m2: mean of the two mean squared distances. precision/recall/fscore: one per tau.
    uncovered_*: holes, the truth area under the face mask where no predicted surface crosses the
    segment +- hole_threshold_m along the truth normal; far_*: the truth area under the mask farther
    than hole_threshold_m from the prediction (this one shrinks a hole by the threshold all round).
    evaluated_area_m2: the truth area under the mask (in per_class entries: all of the class's area).
    per_class: keyed by class name; pred samples count towards the class of their nearest truth face.
    """

    taus_m: tuple[float, ...]
    accuracy: DistanceStats
    completeness: DistanceStats
    chamfer_m: float
    chamfer_l2_m2: float
    precision: tuple[float, ...]
    recall: tuple[float, ...]
    fscore: tuple[float, ...]
    hole_threshold_m: float
    evaluated_area_m2: float
    uncovered_area_m2: float
    uncovered_fraction: float
    far_area_m2: float
    far_fraction: float
    spacing_m: float
    max_distance_m: float | None = None
    per_class: Mapping[str, QualityReport] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """JSON-friendly: plain floats, lists and dicts; NaN and infinity become None."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        out |= {"accuracy": vars(self.accuracy), "completeness": vars(self.completeness),
                "per_class": {k: v.to_dict() for k, v in self.per_class.items()}}
        return _jsonable(out)

    def __str__(self) -> str:
        f = lambda x: f"{x:8.4f}" if math.isfinite(x) else f"{x!s:>8}"
        rows = [f"{'':14}{'mean':>8}{'median':>8}{'p90':>8}{'p95':>8}{'RMS':>8}{'max':>8}  [m]  area m²"]
        for name, s in (("accuracy", self.accuracy), ("completeness", self.completeness)):
            cells = "".join(f(x) for x in (s.mean_m, s.median_m, s.p90_m, s.p95_m, s.rms_m, s.max_m))
            rows.append(f"{name:14}{cells}  {s.area_m2:12.2f}")
        rows.append(f"chamfer {self.chamfer_m:.4f} m, L2 {self.chamfer_l2_m2:.6f} m², "
                    f"spacing {self.spacing_m} m")
        rows.append(f"{'tau m':>8}{'precision':>10}{'recall':>8}{'F':>8}")
        rows += [f"{t:8.3f}{p:10.3f}{r:8.3f}{fs:8.3f}"
                 for t, p, r, fs in zip(self.taus_m, self.precision, self.recall, self.fscore)]
        rows.append(f"uncovered (no surface within +-{self.hole_threshold_m} m along the normal): "
                    f"{self.uncovered_area_m2:.2f} m² of {self.evaluated_area_m2:.2f} m² "
                    f"({100 * self.uncovered_fraction:.1f} %); farther than that: {self.far_area_m2:.2f} m²")
        if self.per_class:
            head = f"{'class':14}{'acc':>8}{'comp':>8}{'F@' + str(self.taus_m[0]):>8}"
            rows.append(f"{head}{'area m²':>12}{'holes m²':>10}")
            for name, r in self.per_class.items():
                rows.append(f"{name:14}{f(r.accuracy.mean_m)}{f(r.completeness.mean_m)}{f(r.fscore[0])}"
                            f"{r.completeness.area_m2:12.2f}{r.uncovered_area_m2:10.2f}")
        return "\n".join(rows)


@dataclass(frozen=True)
class QualityPartial:
    """Mergeable sums behind a QualityReport (one chunk, tile or region): ``(a + b).report()``."""

    accuracy: _Side
    completeness: _Side
    taus_m: tuple[float, ...]
    hole_threshold_m: float
    spacing_m: float
    max_distance_m: float | None
    class_names: tuple[str, ...]

    def __add__(self, other: QualityPartial) -> QualityPartial:
        key = lambda q: (q.taus_m, q.hole_threshold_m, q.class_names)
        if key(self) != key(other):
            raise ValueError("cannot merge partials measured with different taus, thresholds or classes")
        return replace(self, accuracy=self.accuracy + other.accuracy,
                       completeness=self.completeness + other.completeness)

    def report(self) -> QualityReport:
        per_class = {}
        for c, name in enumerate(self.class_names):
            if self.accuracy.n[1 + c] or self.completeness.n[1 + c]:
                per_class[name] = self._report(1 + c, {}, masked=False)
        return self._report(0, per_class, masked=True)

    def _report(self, g: int, per_class: dict, masked: bool) -> QualityReport:
        acc, comp, side = self.accuracy.stats(g), self.completeness.stats(g), self.completeness
        m = int(masked)
        area, holes, far = side.masked[g] if masked else side.w[g], side.holes[g, m], side.far[g, m]
        frac = (lambda x: float(x / area)) if area > 0 else (lambda x: math.nan)
        return QualityReport(
            taus_m=self.taus_m, accuracy=acc, completeness=comp,
            chamfer_m=0.5 * (acc.mean_m + comp.mean_m), chamfer_l2_m2=0.5 * (acc.rms_m**2 + comp.rms_m**2),
            precision=acc.within, recall=comp.within,
            fscore=tuple(_fscore(p, r) for p, r in zip(acc.within, comp.within)),
            hole_threshold_m=self.hole_threshold_m, evaluated_area_m2=float(area),
            uncovered_area_m2=float(holes), uncovered_fraction=frac(holes),
            far_area_m2=float(far), far_fraction=frac(far),
            spacing_m=self.spacing_m, max_distance_m=self.max_distance_m, per_class=per_class,
        )


# ------------------------------------------------------------------------------------------ evaluation

def _validated(vertices, faces, name: str):
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


def _class_names(true_face_class, class_names) -> tuple[str, ...]:
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
    pv, pf = _validated(pred_vertices, pred_faces, "predicted")
    tv, tf = _validated(true_vertices, true_faces, "truth")
    tc = None if true_face_class is None else np.asarray(true_face_class, np.int64)
    mask = np.ones(len(tf), bool) if true_face_mask is None else np.asarray(true_face_mask, bool)
    if len(mask) != len(tf) or (tc is not None and len(tc) != len(tf)):
        raise InputError(None, f"truth face mask/classes must have one entry per truth face ({len(tf)})")
    names, taus = _class_names(tc, class_names), tuple(float(t) for t in taus)
    density = density_per_m2 if density_per_m2 is not None else 1.0 / spacing_m**2
    seed, cap = seed_of(rng), math.inf if max_distance_m is None else float(max_distance_m)
    boxes = sample_boxes(region, tile, tile_size_m)
    acc, comp = _Side.empty(1 + len(names), len(taus)), _Side.empty(1 + len(names), len(taus))
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


def _faces_by_tile(vertices, faces, tile_size_m: float, pad_m: float) -> dict[TileId, np.ndarray]:
    """Faces whose x/y bounding box, grown by pad_m, touches each tile: {TileId: (k,) int64 sorted}."""
    if len(faces) == 0:
        return {}
    corners = [vertices[faces[:, q], :2] for q in range(3)]
    i0 = np.floor((np.minimum.reduce(corners) - pad_m) / tile_size_m).astype(np.int64)
    i1 = np.floor((np.maximum.reduce(corners) + pad_m) / tile_size_m).astype(np.int64)
    nx, ny = i1[:, 0] - i0[:, 0] + 1, i1[:, 1] - i0[:, 1] + 1
    cnt = nx * ny
    face = np.repeat(np.arange(len(faces)), cnt)
    k = np.arange(len(face)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    ix, iy = i0[face, 0] + k % nx[face], i0[face, 1] + k // nx[face]
    order = np.lexsort((face, iy, ix))
    ix, iy, face = ix[order], iy[order], face[order]
    cuts = np.flatnonzero((np.diff(ix) != 0) | (np.diff(iy) != 0)) + 1
    return {TileId(int(ix[s]), int(iy[s])): part for s, part in zip(np.r_[0, cuts], np.split(face, cuts))}


def _submesh(vertices, faces, ids):
    used, inv = np.unique(faces[ids], return_inverse=True)
    return vertices[used], inv.reshape(-1, 3)


@dataclass(frozen=True)
class TiledQuality:
    """Exactly aggregated figures of the whole scene and each ground tile's own figures."""

    total: QualityReport
    tiles: Mapping[TileId, QualityReport]


def evaluate_by_tile(pred_vertices, pred_faces, true_vertices, true_faces, *, tile_size_m: float = 100.0,
                     buffer_m: float = 2.0, true_face_mask=None, true_face_class=None, class_names=None,
                     max_distance_m: float | None = None, rng=0, **kwargs) -> TiledQuality:
    """:func:`evaluate_mesh` tile by tile on the ground grid (TileId), memory bounded by one tile.

    Each sample belongs to the tile that contains it; its distance is measured to the other mesh's
    faces within ``buffer_m`` of the tile, which is exact for distances up to buffer_m, so distances
    are capped at buffer_m (and at max_distance_m). Sums are merged, so ``total`` equals
    ``evaluate_mesh(..., max_distance_m=buffer_m)`` (percentiles to the 0.05 mm histogram bin).
    """
    total, tiles = evaluate_tiles(pred_vertices, pred_faces, true_vertices, true_faces, tile_size_m=tile_size_m,
                                  buffer_m=buffer_m, true_face_mask=true_face_mask, true_face_class=true_face_class,
                                  class_names=class_names, max_distance_m=max_distance_m, rng=rng, **kwargs)
    if total is None:
        pv, pf = _validated(pred_vertices, pred_faces, "predicted")
        tv, tf = _validated(true_vertices, true_faces, "truth")
        names = _class_names(None if true_face_class is None else np.asarray(true_face_class), class_names)
        cap = buffer_m if max_distance_m is None else min(max_distance_m, buffer_m)
        total = evaluate_partial(pv, pf, tv, tf, class_names=names, max_distance_m=cap, rng=seed_of(rng), **kwargs)
    return TiledQuality(total.report(), tiles)


def evaluate_tiles(pred_vertices, pred_faces, true_vertices, true_faces, *, tile_size_m: float = 100.0,
                   buffer_m: float = 2.0, true_face_mask=None, true_face_class=None, class_names=None,
                   max_distance_m: float | None = None, rng=0, part: tuple[int, int] = (0, 1),
                   **kwargs) -> tuple[QualityPartial | None, dict]:
    """The summed partial of the tiles of one share of the scene (``part`` = (k, n): the k-th of n
    interleaved shares of the sorted tiles), and each tile's report; partials of all n shares add up to
    the whole (:func:`evaluate_by_tile`). None when the share holds no tile."""
    pv, pf = _validated(pred_vertices, pred_faces, "predicted")
    tv, tf = _validated(true_vertices, true_faces, "truth")
    tc = None if true_face_class is None else np.asarray(true_face_class, np.int64)
    mask = np.ones(len(tf), bool) if true_face_mask is None else np.asarray(true_face_mask, bool)
    names, seed = _class_names(tc, class_names), seed_of(rng)
    cap = buffer_m if max_distance_m is None else min(max_distance_m, buffer_m)
    owners = set(_faces_by_tile(pv, pf, tile_size_m, 1e-6)) | set(_faces_by_tile(tv, tf, tile_size_m, 1e-6))
    pred_near = _faces_by_tile(pv, pf, tile_size_m, buffer_m)
    true_near = _faces_by_tile(tv, tf, tile_size_m, buffer_m)
    none = np.zeros(0, np.int64)
    total, tiles = None, {}
    k, n = part
    for tile in sorted(owners)[k::n]:
        pi, ti = pred_near.get(tile, none), true_near.get(tile, none)
        p = evaluate_partial(*_submesh(pv, pf, pi), *_submesh(tv, tf, ti), tile=tile,
                             tile_size_m=tile_size_m,
                             true_face_mask=mask[ti], true_face_class=None if tc is None else tc[ti],
                             class_names=names, max_distance_m=cap, rng=seed, **kwargs)
        if p.accuracy.n[0] or p.completeness.n[0]:
            tiles[tile] = p.report()
        total = p if total is None else total + p
    return total, tiles


__all__ = [
    "FACADE_CLASS_IDS",
    "DistanceStats",
    "QualityPartial",
    "QualityReport",
    "TiledQuality",
    "closest_points_on_triangles",
    "evaluate_by_tile",
    "evaluate_mesh",
    "evaluate_partial",
    "evaluate_tiles",
    "facade_mask",
    "face_areas",
    "point_to_mesh_distance",
    "sample_counts",
    "sample_surface",
    "sample_weights",
]
