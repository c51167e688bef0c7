"""Area-weighted, stratified, deterministic samples of a triangle surface (used by quality and registration).

Face f receives ``sample_counts`` samples, each standing for area_f / count_f m², so sums of sample
weights equal surface areas exactly. Sample j of a face is a Cranley-Patterson-rotated R2 point whose
offset is hashed from the seed and the face's geometry, so any subset, chunking or tiling of the faces
gives bit-identical samples.

    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0]], float)
    >>> pts, face = sample_surface(v, np.array([[0, 1, 2]]), spacing_m=0.5)
    >>> len(pts), bool((pts[:, :2].sum(1) <= 2).all())
    (8, True)
"""

from __future__ import annotations

import numpy as np

from ms3d_model.hashing import splitmix64 as _splitmix64
from storage.ids import TileId
from tasks.geometry.triangles import face_areas

_R2 = np.array([1 / 1.32471795724474602596, 1 / 1.32471795724474602596**2])  # Roberts' R2 sequence


def sample_counts(areas: np.ndarray, density_per_m2: float) -> np.ndarray:
    """Samples per face: round(area * density), at least 1 on every face of positive area.

    areas: (m,) float64 m² -> (m,) int64. Each sample then stands for area / count m², so sums of
    sample weights equal surface areas exactly, even for faces far smaller than the spacing.
    """
    n = np.rint(areas * density_per_m2).astype(np.int64)
    return np.where(areas > 0, np.maximum(n, 1), 0)


def seed_of(rng) -> int:
    """A seed (int), a Generator (one draw) or None (0) -> an int seed."""
    if isinstance(rng, np.random.Generator):
        return int(rng.integers(0, 2**62))
    return 0 if rng is None else int(rng)


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


def iter_surface_samples(vertices, faces, face_ids, density, seed, chunk_size):
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
    chunks = list(iter_surface_samples(vertices, faces, ids, density, seed_of(rng), 1 << 62))
    if not chunks:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return chunks[0][0], chunks[0][1]


def sample_weights(vertices, faces, face_idx, spacing_m: float = 0.02, density_per_m2=None) -> np.ndarray:
    """(k,) float64 m² that each sample of :func:`sample_surface` stands for (sums to the area)."""
    density = density_per_m2 if density_per_m2 is not None else 1.0 / spacing_m**2
    areas = face_areas(vertices, faces[face_idx])
    return areas / sample_counts(areas, density)


def sample_faces(vertices, faces, counts, rng=0) -> tuple[np.ndarray, np.ndarray]:
    """``counts[f]`` samples on each face f: the same stratified, deterministic sequence as
    :func:`sample_surface`, with the number per face chosen by the caller.

    vertices: (n, 3) float64 metres; faces: (m, 3) int64; counts: (m,) int >= 0; rng: seed or Generator.
    Returns points (k, 3) float64 and face_idx (k,) int64, k = counts.sum(), grouped by face in face order.
    """
    vertices, faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    counts = np.asarray(counts, np.int64)
    ids = np.flatnonzero(counts > 0)
    if len(ids) == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    c = counts[ids]
    cum = np.cumsum(c)
    keys = _face_keys(vertices, faces[ids])
    pts, k = _sample_range(vertices, faces, ids, keys, cum, cum - c, seed_of(rng), 0, int(cum[-1]))
    return pts, ids[k]


def _systematic_round(expected: np.ndarray, offset: float) -> np.ndarray:
    """Integer counts (m,) int64 whose running sums follow those of ``expected`` (m,) float64: each is the
    floor or the ceiling of its value, and they add up to the rounded total (systematic sampling)."""
    edges = np.floor(np.concatenate([[0.0], np.cumsum(expected)]) + offset).astype(np.int64)
    return np.diff(edges)


def budget_sample_counts(areas: np.ndarray, density_per_m2: float, max_samples: int, rng=0) -> np.ndarray:
    """Samples per face at ``density_per_m2``, at most ``max_samples`` in all. (m,) float64 m² -> (m,) int64.

    Each face gets area x density samples rounded systematically (the floor or the ceiling, so totals
    are exact even when every face is smaller than the spacing, with no rounding bias), and at least
    one when it has positive area. Over the budget, while every face of positive area can still have
    one sample, the same rule at the highest lower density that fits (bisection); otherwise (more
    faces than the budget) exactly ``max_samples`` samples, area-proportional, and small faces may get
    none. Deterministic: the rounding offset is drawn from ``rng`` (seed, Generator or None).

    >>> budget_sample_counts(np.array([1.0, 3.0, 0.0, 1e-6]), 4.0, 100).tolist()
    [4, 12, 0, 1]
    >>> budget_sample_counts(np.array([1.0, 3.0, 0.0, 1e-6]), 4.0, 9).tolist()
    [2, 6, 0, 1]
    >>> budget_sample_counts(np.array([1.0, 3.0, 0.0, 1e-6]), 4.0, 2).tolist()  # 0.5 and 1.5 expected
    [0, 2, 0, 0]
    """
    areas = np.asarray(areas, np.float64)
    areas = np.where(np.isfinite(areas) & (areas > 0), areas, 0.0)
    offset = float(_hash_uniforms(seed_of(rng), np.zeros(1, np.int64))[0, 0])
    positive = areas > 0

    def counts_at(density: float) -> np.ndarray:
        return np.where(positive, np.maximum(_systematic_round(areas * density, offset), 1), 0)

    counts = counts_at(density_per_m2)
    if counts.sum() <= max_samples:
        return counts
    n_faces, total = np.count_nonzero(positive), areas.sum()
    if n_faces <= max_samples:
        # the total lies between total x density - 1 and that + n_faces, which brackets the density
        lo, hi = max(0.0, (max_samples - n_faces) / total), min(float(density_per_m2), (max_samples + 1) / total)
        for _ in range(30):
            if hi - lo <= 1e-4 * hi:
                break
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if counts_at(mid).sum() <= max_samples else (lo, mid)
        return counts_at(lo)
    return _systematic_round(areas * (max_samples / total), offset)


# --------------------------------------------------------------------- samples of a region or tile


def sample_boxes(region, tile: TileId | None, tile_size_m: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Half-open boxes [lo, hi) a sample must lie in: region (xmin, ymin, xmax, ymax) or 3D, and the tile."""
    out = []
    if region is not None:
        r = np.asarray(region, np.float64)
        out.append((r[: len(r) // 2], r[len(r) // 2 :]))
    if tile is not None:
        lo = np.array([tile.ix, tile.iy], np.float64) * tile_size_m
        out.append((lo, lo + tile_size_m))
    return out


def faces_in_boxes(vertices, faces, boxes) -> np.ndarray:
    """Indices of faces whose bounding box touches every box (1 µm slack for rounding of samples)."""
    ids = np.arange(len(faces))
    for lo, hi in boxes:
        k = len(lo)
        corners = [vertices[faces[ids, q], :k] for q in range(3)]
        touch = (np.minimum.reduce(corners) <= hi + 1e-6) & (np.maximum.reduce(corners) >= lo - 1e-6)
        ids = ids[touch.all(1)]
    return ids


def samples_inside(points, boxes, tile: TileId | None, tile_size_m: float) -> np.ndarray:
    """(k,) bool: points (k, 3) inside every box of :func:`sample_boxes`; the tile test uses its floor()."""
    keep = np.ones(len(points), bool)
    for lo, hi in boxes[: len(boxes) - (tile is not None)]:
        keep &= ((points[:, : len(lo)] >= lo) & (points[:, : len(lo)] < hi)).all(1)
    if tile is not None:  # the same floor() that assigns samples to tiles, so tiles partition exactly
        ij = np.floor(points[:, :2] / tile_size_m)
        keep &= (ij[:, 0] == tile.ix) & (ij[:, 1] == tile.iy)
    return keep


__all__ = [
    "budget_sample_counts",
    "faces_in_boxes",
    "iter_surface_samples",
    "sample_boxes",
    "sample_counts",
    "sample_faces",
    "sample_surface",
    "sample_weights",
    "samples_inside",
    "seed_of",
]
