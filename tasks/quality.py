"""Measured accuracy of a mesh against the truth mesh: accuracy, completeness, Chamfer, F-score, holes.

Both surfaces are sampled (area-weighted, stratified, deterministic) and each sample's exact unsigned
distance to the other mesh is measured with open3d's ``RaycastingScene`` (float32, queried in a frame
centred on the data) and refined in float64 on the face it returns. Everything is accumulated as
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
import open3d as o3d

from storage.errors import InputError
from storage.ids import TileId

# synth.scene.FaceClass values of facade faces: WALL, GLASS, FRAME, BALCONY, EAVE.
FACADE_CLASS_IDS = (2, 4, 5, 6, 7)

_R2 = np.array([1 / 1.32471795724474602596, 1 / 1.32471795724474602596**2])  # Roberts' R2 sequence
_FINE_STEP, _FINE_MAX, _N_FINE = 5e-5, 0.5, 10_000
_RATIO, _N_COARSE = 1.001, 12_208  # 0.5 m .. 100 km, then one overflow bin
_N_BINS = _N_FINE + _N_COARSE + 1


# ----------------------------------------------------------------------------------------- geometry

def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """vertices: (n, 3) float64 metres; faces: (m, 3) int64 -> (m,) float64 m²."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def sample_counts(areas: np.ndarray, density_per_m2: float) -> np.ndarray:
    """Samples per face: round(area * density), at least 1 on every face of positive area.

    areas: (m,) float64 m² -> (m,) int64. Each sample then stands for area / count m², so sums of
    sample weights equal surface areas exactly, even for faces far smaller than the spacing.
    """
    n = np.rint(areas * density_per_m2).astype(np.int64)
    return np.where(areas > 0, np.maximum(n, 1), 0)


def _seed_of(rng) -> int:
    if isinstance(rng, np.random.Generator):
        return int(rng.integers(0, 2**62))
    return 0 if rng is None else int(rng)


def _splitmix64(x: np.ndarray) -> np.ndarray:
    """splitmix64 finaliser, elementwise on uint64 (wrapping arithmetic)."""
    z = x + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def _hash_uniforms(seed: int, keys: np.ndarray) -> np.ndarray:
    """Two uniforms in [0, 1) per key: (n,) int64 -> (n, 2) float64, a pure function of (seed, key)."""
    h = _splitmix64(keys.view(np.uint64) ^ np.uint64(seed % 2**64))
    z = _splitmix64(h[:, None] + np.arange(1, 3, dtype=np.uint64))
    return (z >> np.uint64(11)).astype(np.float64) * 2.0**-53


def _face_keys(vertices, faces) -> np.ndarray:
    """(m,) int64 key per face from its edge vectors at 1 mm: independent of face order, of the
    subset or tile a face comes in, and of a translation of the whole mesh."""
    a = vertices[faces[:, 0]]
    q = np.rint(np.concatenate([vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a], 1) * 1e3)
    h = np.zeros(len(faces), np.uint64)
    for col in np.ascontiguousarray(q.astype(np.int64).T).view(np.uint64):
        h = _splitmix64(h ^ col)
    return h.view(np.int64)


def _sample_range(vertices, faces, face_ids, keys, cum, start, seed, lo, hi):
    """Samples lo..hi-1 of the concatenated per-face sample sequences.

    face_ids: (k,) face indices to sample; keys: (k,) their :func:`_face_keys`; cum, start: (k,)
    int64 cumulative sample counts of those faces, after and before each. Sample j of a face is a
    Cranley-Patterson-rotated R2 point (offset hashed from seed and the face key) mapped
    area-preservingly onto the triangle, so it depends only on (seed, face geometry, j): any subset,
    chunking or tiling gives bit-identical samples.
    """
    idx = np.arange(lo, hi, dtype=np.int64)
    k = np.searchsorted(cum, idx, side="right")
    j = (idx - start[k]).astype(np.float64)
    fid = face_ids[k]
    r = (_hash_uniforms(seed, keys[k]) + j[:, None] * _R2) % 1.0
    s = np.sqrt(r[:, 0])
    b1, b2 = s * (1.0 - r[:, 1]), s * r[:, 1]
    a, b, c = (vertices[faces[fid, q]] for q in range(3))
    return a + b1[:, None] * (b - a) + b2[:, None] * (c - a), k


def _sampler(vertices, faces, face_ids, density, seed, chunk_size):
    """Yield (points (c, 3) float64, face_idx (c,) int64, weights (c,) float64 m²) in chunks."""
    areas = face_areas(vertices, faces[face_ids])
    counts = sample_counts(areas, density)
    keep = counts > 0
    face_ids, areas, counts = face_ids[keep], areas[keep], counts[keep]
    weight = areas / np.maximum(counts, 1)
    cum, keys = np.cumsum(counts), _face_keys(vertices, faces[face_ids])
    start, total = cum - counts, int(cum[-1]) if len(cum) else 0
    for lo in range(0, total, chunk_size):
        hi = min(lo + chunk_size, total)
        pts, k = _sample_range(vertices, faces, face_ids, keys, cum, start, seed, lo, hi)
        yield pts, face_ids[k], weight[k]


def sample_surface(vertices, faces, spacing_m: float = 0.02, rng=0, face_mask=None, density_per_m2=None):
    """Area-weighted, stratified, deterministic samples of a triangle surface.

    vertices: (n, 3) float64 metres; faces: (m, 3) int64; face_mask: (m,) bool or None (all faces);
    density_per_m2 overrides ``spacing_m`` (density = 1 / spacing²); rng: seed or Generator.
    Returns points (k, 3) float64 in the input frame and face_idx (k,) int64. Face f receives
    ``sample_counts`` samples, each of weight area_f / count_f (see :func:`sample_weights`).
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    density = density_per_m2 if density_per_m2 is not None else 1.0 / spacing_m**2
    ids = np.arange(len(faces)) if face_mask is None else np.flatnonzero(face_mask)
    chunks = list(_sampler(vertices, faces, ids, density, _seed_of(rng), 1 << 62))
    if not chunks:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return chunks[0][0], chunks[0][1]


def sample_weights(vertices, faces, face_idx, spacing_m: float = 0.02, density_per_m2=None) -> np.ndarray:
    """(k,) float64 m² that each sample of :func:`sample_surface` stands for (sums to the area)."""
    density = density_per_m2 if density_per_m2 is not None else 1.0 / spacing_m**2
    areas = face_areas(vertices, faces[face_idx])
    return areas / sample_counts(areas, density)


def closest_points_on_triangles(p, a, b, c) -> np.ndarray:
    """Closest point of each triangle (a, b, c) to p, all (n, 3) float64 -> (n, 3) float64.

    Vectorised form of the Voronoi-region test in Ericson, Real-Time Collision Detection, 5.1.5.
    """
    dot = lambda x, y: np.einsum("ij,ij->i", x, y)
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2, d3, d4, d5, d6 = dot(ab, ap), dot(ac, ap), dot(ab, bp), dot(ac, bp), dot(ab, cp), dot(ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        den = va + vb + vc
        v, w = vb / den, vc / den  # interior
        regions = [  # first match wins, as in the scalar original
            ((d1 <= 0) & (d2 <= 0), 0.0, 0.0),
            ((d3 >= 0) & (d4 <= d3), 1.0, 0.0),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), d1 / (d1 - d3), 0.0),
            ((d6 >= 0) & (d5 <= d6), 0.0, 1.0),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), 0.0, d2 / (d2 - d6)),
        ]
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        regions.append(((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), 1.0 - t, t))
        for cond, rv, rw in reversed(regions):
            v, w = np.where(cond, rv, v), np.where(cond, rw, w)
    return a + v[:, None] * ab + w[:, None] * ac


def _unit_normals(vertices, faces) -> np.ndarray:
    """(m, 3) float64 unit normals of faces (m, 3) int64 (zero for degenerate faces)."""
    a = vertices[faces[:, 0]]
    n = np.cross(vertices[faces[:, 1]] - a, vertices[faces[:, 2]] - a)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)


class _MeshDistance:
    """An open3d scene over faces of a mesh, in a float64 frame centred on them (float32 inside)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        used, inv = np.unique(faces, return_inverse=True)
        self.faces = inv.reshape(-1, 3)
        v = vertices[used]
        self.centre = 0.5 * (v.min(0) + v.max(0)) if len(v) else np.zeros(3)
        self.vertices = v - self.centre
        self.scene = None
        if len(self.faces):
            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                                     o3d.core.Tensor(self.faces.astype(np.uint32)))

    def query(self, points: np.ndarray, exact: bool = True):
        """points: (k, 3) float64 input frame -> distances (k,) float64 m, face ids (k,) int64 (-1: none)."""
        if self.scene is None:
            return np.full(len(points), np.inf), np.full(len(points), -1, np.int64)
        p = points - self.centre
        out = self.scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        prim = out["primitive_ids"].numpy().astype(np.int64)
        ok = prim < len(self.faces)  # INVALID_ID (2**32 - 1) when nothing was found
        d = np.linalg.norm(p - out["points"].numpy().astype(np.float64), axis=1)
        d[~ok] = np.inf
        if exact and ok.any():
            tri = self.vertices[self.faces[prim[ok]]]
            q = closest_points_on_triangles(p[ok], tri[:, 0], tri[:, 1], tri[:, 2])
            d64 = np.linalg.norm(p[ok] - q, axis=1)
            d[ok] = np.where(np.isfinite(d64), d64, d[ok])  # degenerate faces keep the float32 value
        return d, np.where(ok, prim, -1)

    def covered_along(self, points: np.ndarray, normals: np.ndarray, half_m: float) -> np.ndarray:
        """(k,) bool: the mesh crosses the segment points +- half_m * normals ((k, 3) unit vectors)."""
        if self.scene is None or len(points) == 0:
            return np.zeros(len(points), bool)
        rays = np.concatenate([points - self.centre - half_m * normals, normals], 1).astype(np.float32)
        return self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() <= 2 * half_m


def point_to_mesh_distance(points, vertices, faces, *, return_faces=False, exact=True, chunk_size=1_000_000):
    """Exact unsigned distance from each point to a triangle set.

    points: (k, 3) float64 metres; vertices: (n, 3) float64 metres, same frame; faces: (m, 3) int64.
    Returns (k,) float64 metres (inf when the mesh is empty), and with ``return_faces`` also the
    (k,) int64 index of the closest face (-1 when none). Large world coordinates are safe: open3d
    works in float32 around the mesh's centre and ``exact`` re-measures on the found face in float64.
    """
    points, vertices = np.asarray(points, np.float64), np.asarray(vertices, np.float64)
    md = _MeshDistance(vertices, np.asarray(faces, np.int64))
    d, fid = np.empty(len(points)), np.empty(len(points), np.int64)
    for lo in range(0, len(points), chunk_size):
        d[lo:lo + chunk_size], fid[lo:lo + chunk_size] = md.query(points[lo:lo + chunk_size], exact)
    return (d, fid) if return_faces else d


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


def _boxes(region, tile: TileId | None, tile_size_m: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Half-open boxes [lo, hi) a sample must lie in: region (xmin, ymin, xmax, ymax) or 3D, and the tile."""
    out = []
    if region is not None:
        r = np.asarray(region, np.float64)
        out.append((r[: len(r) // 2], r[len(r) // 2:]))
    if tile is not None:
        lo = np.array([tile.ix, tile.iy], np.float64) * tile_size_m
        out.append((lo, lo + tile_size_m))
    return out


def _faces_in_boxes(vertices, faces, boxes) -> np.ndarray:
    """Indices of faces whose bounding box touches every box (1 µm slack for rounding of samples)."""
    ids = np.arange(len(faces))
    for lo, hi in boxes:
        k = len(lo)
        corners = [vertices[faces[ids, q], :k] for q in range(3)]
        touch = (np.minimum.reduce(corners) <= hi + 1e-6) & (np.maximum.reduce(corners) >= lo - 1e-6)
        ids = ids[touch.all(1)]
    return ids


def _inside(points, boxes, tile: TileId | None, tile_size_m: float) -> np.ndarray:
    keep = np.ones(len(points), bool)
    for lo, hi in boxes[: len(boxes) - (tile is not None)]:
        keep &= ((points[:, : len(lo)] >= lo) & (points[:, : len(lo)] < hi)).all(1)
    if tile is not None:  # the same floor() that assigns samples to tiles, so tiles partition exactly
        ij = np.floor(points[:, :2] / tile_size_m)
        keep &= (ij[:, 0] == tile.ix) & (ij[:, 1] == tile.iy)
    return keep


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
    seed, cap = _seed_of(rng), math.inf if max_distance_m is None else float(max_distance_m)
    boxes = _boxes(region, tile, tile_size_m)
    acc, comp = _Side.empty(1 + len(names), len(taus)), _Side.empty(1 + len(names), len(taus))
    for side, (sv, sf), (ov, of), salt in ((acc, (pv, pf), (tv, tf), 0), (comp, (tv, tf), (pv, pf), 1)):
        other = _MeshDistance(ov, of)
        for pts, fid, w in _sampler(sv, sf, _faces_in_boxes(sv, sf, boxes), density, seed ^ salt, chunk_size):
            keep = _inside(pts, boxes, tile, tile_size_m)
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
                holes = ~other.covered_along(pts, _unit_normals(sv, sf[fid]), hole_threshold_m)
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
    pv, pf = _validated(pred_vertices, pred_faces, "predicted")
    tv, tf = _validated(true_vertices, true_faces, "truth")
    tc = None if true_face_class is None else np.asarray(true_face_class, np.int64)
    mask = np.ones(len(tf), bool) if true_face_mask is None else np.asarray(true_face_mask, bool)
    names, seed = _class_names(tc, class_names), _seed_of(rng)
    cap = buffer_m if max_distance_m is None else min(max_distance_m, buffer_m)
    owners = set(_faces_by_tile(pv, pf, tile_size_m, 1e-6)) | set(_faces_by_tile(tv, tf, tile_size_m, 1e-6))
    pred_near = _faces_by_tile(pv, pf, tile_size_m, buffer_m)
    true_near = _faces_by_tile(tv, tf, tile_size_m, buffer_m)
    none = np.zeros(0, np.int64)
    total, tiles = None, {}
    for tile in sorted(owners):
        pi, ti = pred_near.get(tile, none), true_near.get(tile, none)
        part = evaluate_partial(*_submesh(pv, pf, pi), *_submesh(tv, tf, ti), tile=tile,
                                tile_size_m=tile_size_m,
                                true_face_mask=mask[ti], true_face_class=None if tc is None else tc[ti],
                                class_names=names, max_distance_m=cap, rng=seed, **kwargs)
        if part.accuracy.n[0] or part.completeness.n[0]:
            tiles[tile] = part.report()
        total = part if total is None else total + part
    if total is None:
        total = evaluate_partial(pv, pf, tv, tf, class_names=names, max_distance_m=cap, rng=seed, **kwargs)
    return TiledQuality(total.report(), tiles)
