"""Hand-made geometric cues of a (mesh patch, point patch) pair: the non-deep baseline's features and the
extra input of MS3DQE-Net+.

All in metres, from the raw (unsampled) patch: how far the MLS points lie from the mesh (from the nearest
face of the whole tile when the tile's surface is given, as the classify stage and training give it: a point
near a patch's side is often nearest to a face of the next cell; measured on the pair's own faces, a real
production's clean facade read up to 15 cm off at patch borders) and the mesh from the points (both ways), how much of the mesh the MLS covers, open (boundary) edges, normal agreement,
planarity, counts. In the spirit of Ennafii et al. (PE&RS 2019): cheap, interpretable, and the honest bar a
network has to clear.

``open_edges`` (per face, per edge) says whether the edge has no other face in the whole tile (a real
mesh boundary: a hole), as opposed to the patch's own cut; a face whose neighbour lies in the next tile
counts as open too (rare: only along tile borders).

Vectorised over pairs: a batch's points and faces are concatenated as contiguous runs, one per pair; the
nearest searches stay within a pair (a small k-d tree per pair for the point -> face candidates, a grid per
pair for the mesh -> point distances, :mod:`ms3d_model.grid_search`); per-pair means, sums and maxima are
segment reductions (``np.bincount``, ``reduceat``), and the per-pair sorts, covariances and seeded subsamples
(of a pair above ``MAX_CUE_POINTS`` points) are compiled loops over the runs (:mod:`ms3d_model.cue_kernels`).
The numbers
equal the per-pair loop this replaced (tests/ms3d_model/test_cues.py keeps it as the reference), except
that a zero-area face now gives distances to its longest side instead of NaN.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .cue_kernels import run_covariances, run_starts, subset_runs
from .features import edge_neighbours, pair_seed, vertex_ids_from_coords
from .grid_search import nearest_distance_runs
from .kernels import nearest_of_candidates
from .segments import median_of_sorted, percentile_of_sorted, segment_max, segment_mean, sorted_segments
from .surface import TileSurface, in_plane

CUE_NAMES = (
    "log_n_points", "log_n_faces", "mesh_area_m2", "log_point_density",
    "p2m_mean", "p2m_median", "p2m_p90", "p2m_max", "p2m_frac_5cm", "p2m_frac_15cm",
    "p2m_signed_median", "p2m_signed_mean",
    "m2p_mean", "m2p_p90", "m2p_max", "coverage_10cm",
    "patch_boundary_m", "open_edge_m", "open_edge_count",
    "normal_agreement", "point_planarity", "mesh_normal_spread",
    "point_spread_along_normal", "mesh_spread_along_normal", "frac_horizontal_faces",
)
# Appended later (a model trained on the first 25 reads only those: TreeNet indexes its features, MS3DQE-Net+
# takes the first ``n_cues`` columns). Signed distances are positive in front of the mesh (along its normal).
EXTRA_CUE_NAMES = (
    "p2m_frac_behind_10cm", "p2m_frac_front_10cm", "p2m_frac_30cm", "p2m_p25", "p2m_p75",
    "p2m_signed_p10", "p2m_signed_p90", "m2p_median", "m2p_frac_25cm",
    "points_above_mesh_m", "points_below_mesh_m",
)
PAIR_CUE_NAMES = CUE_NAMES + EXTRA_CUE_NAMES  # what one pair alone gives (:func:`batch_cues`)
N_PAIR_CUES = len(PAIR_CUE_NAMES)
# Appended last: the pair's neighbourhood in its tile (:mod:`ms3d_model.context`), the max and mean of these
# pair cues over the pairs in the 26 neighbouring cells, and how many there are. A defect spans several cells;
# a cell whose own evidence is weak is bad far more often when its neighbours are.
CONTEXT_SOURCES = ("p2m_frac_15cm", "p2m_p90", "coverage_10cm", "open_edge_m", "m2p_p90",
                   "p2m_frac_behind_10cm", "p2m_frac_front_10cm", "m2p_frac_25cm")
CONTEXT_CUE_NAMES = (tuple(f"nb_max_{n}" for n in CONTEXT_SOURCES) + tuple(f"nb_mean_{n}" for n in CONTEXT_SOURCES)
                     + ("nb_count",))
# Appended after those: the pair's points against the tile's whole surface (:mod:`ms3d_model.surface`): the
# share more than 10 cm from every face of the tile, the share more than 10 cm *beside* the surface (their
# offset mostly in the nearest face's plane: the scan sees surface where the mesh has none), and the 90th
# percentile of the in-plane offset (m); then the max and mean of the in-plane share over the neighbours.
SURFACE_CUE_NAMES = ("surf_p2m_frac_10cm", "surf_lateral_frac_10cm", "surf_lateral_p90")
SURFACE_CONTEXT_SOURCES = ("surf_lateral_frac_10cm",)
SURFACE_CONTEXT_NAMES = (tuple(f"nb_max_{n}" for n in SURFACE_CONTEXT_SOURCES)
                         + tuple(f"nb_mean_{n}" for n in SURFACE_CONTEXT_SOURCES))
OWN_CUE_NAMES = PAIR_CUE_NAMES + SURFACE_CUE_NAMES  # what :func:`batch_cues` gives per pair, in this order
# Appended last: the pair's offset from the mesh against its neighbours' (:mod:`ms3d_model.context`): the mean of
# these signed and unsigned distance statistics over the pairs in the 26 neighbouring cells ("around_"), and the
# pair's own value minus that mean ("vs_around_"). A dent or a warp moves the scan a few centimetres off the mesh
# over a few cells, as range noise and registration do everywhere; the difference from the neighbourhood tells
# the two apart without reading the mesh's own shape.
RELATIVE_SOURCES = ("p2m_signed_median", "p2m_signed_mean", "p2m_signed_p10", "p2m_signed_p90", "p2m_median")
RELATIVE_CUE_NAMES = tuple(f"around_{n}" for n in RELATIVE_SOURCES) + tuple(f"vs_around_{n}" for n in RELATIVE_SOURCES)
CUE_NAMES = PAIR_CUE_NAMES + CONTEXT_CUE_NAMES + SURFACE_CUE_NAMES + SURFACE_CONTEXT_NAMES + RELATIVE_CUE_NAMES
N_CUES = len(CUE_NAMES)
LATERAL_MIN_M = 0.10  # the offsets the surface cues count (a crack or a seam leaves millimetres)
MAX_CUE_POINTS = 1024
# The cues over a pair's whole point set (mesh -> point distances, the points' normal and planarity, their
# spread along the mesh normal) use at most this many of its points, a seeded subsample above it; counts and
# z extents use every point. Real MLS density puts up to ~130 k points in a pair (10 % above the cap at
# density 1.0), the demo preset at its training density none (seed 7: 12,860 at most), so the shipped models'
# cues are unchanged there.
MAX_SHAPE_POINTS = 16384


def _dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(q,) row-wise dot products of (q, 3) arrays (``(u * v).sum(1)`` without the (q, 3) temporary)."""
    return np.einsum("ij,ij->i", u, v)


def open_edge_flags(vids: np.ndarray) -> np.ndarray:
    """(m, 3) bool: edge (v_j, v_{j+1}) of each face is used by no other face of ``vids`` (m, 3) int64.

    ``edge_neighbours(vids) == own face``, computed with a third of its memory (a whole tile's faces):
    a stable sort of the edge keys keeps faces ascending within an edge, as its face tiebreak does, and
    the face across an edge is the next one in the edge's run (cyclic).

    >>> open_edge_flags(np.array([[0, 1, 2], [2, 1, 3]])).tolist()
    [[True, False, True], [False, True, True]]
    """
    vids = np.asarray(vids, np.int64)
    n = 3 * len(vids)
    if n == 0:
        return np.zeros((0, 3), bool)
    b = np.roll(vids, -1, axis=1)
    lo, hi = np.minimum(vids, b).ravel(), np.maximum(vids, b).ravel()
    del b
    order = np.lexsort((hi, lo))
    lo, hi = lo[order], hi[order]
    new_run = np.ones(n, bool)
    new_run[1:] = (lo[1:] != lo[:-1]) | (hi[1:] != hi[:-1])
    del lo, hi
    face = order // 3
    across = np.empty_like(face)
    across[:-1] = face[1:]
    run_end = np.append(new_run[1:], True)
    across[run_end] = face[new_run]  # the k-th run's end wraps to the k-th run's start
    out = np.empty(n, bool)
    out[order] = face == across
    return out.reshape(-1, 3)


def _group_seeds(n_points, keys, seed):
    # a per-pair seed only where it is used (pairs above MAX_CUE_POINTS subsample their points)
    return [pair_seed(seed, int(k)) if n > MAX_CUE_POINTS else 0 for n, k in zip(n_points, keys)]


def _cue_points(p_all: np.ndarray, counts: np.ndarray, seeds: list) -> tuple[np.ndarray, ...]:
    """The pairs' points for the point -> mesh distances (at most ``MAX_CUE_POINTS`` per pair) and for the
    whole-point-set cues (at most ``MAX_SHAPE_POINTS``): (q, 3) float64, their (q,) pair index, then the same
    for the shape set. A pair above a cap gives a seeded subsample.

    p_all: (n, 3) float64, the pairs' points as contiguous runs of ``counts`` (B,) rows. The subset is
    ``order_free_subset`` of each pair (chosen by the points' coordinates, not their rows: any input order,
    same cues), both sizes in one compiled pass."""
    b = len(counts)
    g_all = np.repeat(np.arange(b), counts)
    if counts.max() <= MAX_CUE_POINTS:
        return p_all, g_all, p_all, g_all
    seeds64 = np.array([int(s) % 2**64 for s in seeds], np.uint64)
    cue, shape = subset_runs(np.ascontiguousarray(p_all, np.float64).view(np.uint64), seeds64, run_starts(counts),
                             MAX_CUE_POINTS, MAX_SHAPE_POINTS)
    if counts.max() <= MAX_SHAPE_POINTS:
        return p_all[cue], np.repeat(np.arange(b), np.minimum(counts, MAX_CUE_POINTS)), p_all, g_all
    return (p_all[cue], np.repeat(np.arange(b), np.minimum(counts, MAX_CUE_POINTS)),
            p_all[shape], np.repeat(np.arange(b), np.minimum(counts, MAX_SHAPE_POINTS)))


def _pair_knn(data: np.ndarray, d_counts: np.ndarray, queries: np.ndarray, q_counts: np.ndarray, k: int
             ) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest rows of ``data`` in the same pair for each row of ``queries`` (both (·, 3) float64, pairs
    in contiguous runs of ``d_counts`` / ``q_counts`` (B,) rows): (q, k) float64 distances, nearest first,
    and (q, k) int64 rows of ``data``; inf and ``len(data)`` past a pair's last row (as cKDTree pads).

    One small 3D k-d tree per pair (sliding-midpoint splits: ~2x faster to build than median splits,
    queries exact). One tree over every pair, the pair lifted onto a fourth axis, gives the same neighbours
    (the fourth term of a distance within a pair is exactly 0) at ~1.2x the time: a deeper tree, and the
    (n, 4) copies (``benchmarks/cue_kernel_bench.py``)."""
    dist = np.full((len(queries), k), np.inf)
    rows = np.full((len(queries), k), len(data), np.int64)
    d_start, q_start = run_starts(d_counts), run_starts(q_counts)
    for g in range(len(d_counts)):
        a, e, qa, qe = d_start[g], d_start[g + 1], q_start[g], q_start[g + 1]
        if e == a or qe == qa:
            continue
        kk = min(k, e - a)
        dd, ii = cKDTree(data[a:e], balanced_tree=False, compact_nodes=False).query(queries[qa:qe], k=kk)
        dist[qa:qe, :kk] = dd.reshape(qe - qa, kk)
        rows[qa:qe, :kk] = ii.reshape(qe - qa, kk) + a
    return dist, rows


def _point_to_mesh(p, p_counts, t, f_counts, normals, centres, k_max) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unsigned and signed distances (q,) float64 of points p (q, 3) to their pair's faces: exact distance to
    the nearest of the (up to) k_max faces with the nearest centres; third, the offset along that face's
    normal (q,).

    The exact distance is computed for the nearest-centre face, then only for the candidates whose lower
    bound (centre distance minus the face's radius, and the distance to its plane) is below it: the others
    cannot be nearer, so the result equals computing them all (a tie keeps the earlier candidate either way).
    """
    dc, fi = _pair_knn(centres, f_counts, p, p_counts, min(k_max, int(f_counts.max())))
    radius = np.linalg.norm(t - centres[:, None], axis=2).max(axis=1)
    return nearest_of_candidates(p, t, normals, radius, fi.astype(np.int64), dc)  # compiled: one pass


def _point_normals(p_all, counts, mesh_n) -> tuple[np.ndarray, np.ndarray]:
    """(B, 3) least-variance direction of each pair's points and (B,) planarity (smallest eigenvalue over
    the sum; 0 and the mesh normal below 3 points). p_all: (n, 3) float64 in contiguous runs of counts (B,)."""
    _, cov = run_covariances(p_all, run_starts(counts))  # compiled; the sums bincount gave, in its order
    ev, evec = np.linalg.eigh(cov)
    ok = counts >= 3
    pt_n = np.where(ok[:, None], evec[:, :, 0], mesh_n)
    planarity = np.where(ok, np.maximum(ev[:, 0], 0.0) / np.maximum(ev.sum(1), 1e-12), 0.0)
    return pt_n, planarity


def _surface_cues(d: np.ndarray, off: np.ndarray, gp: np.ndarray, n_cue: np.ndarray, b: int) -> list:
    """The :data:`SURFACE_CUE_NAMES` columns, (B,) float64 each, from the cue points' distances d (q,) and
    normal offsets off (q,) to the surface, the points of pair gp (q,), n_cue (B,) of them per pair."""
    lat = in_plane(d, off)
    beside = (lat > LATERAL_MIN_M) & (lat > np.abs(off))
    return [segment_mean((d > LATERAL_MIN_M).astype(float), gp, n_cue), segment_mean(beside.astype(float), gp, n_cue),
            percentile_of_sorted(sorted_segments(lat, gp, b), 90)]


def _cues(points: list, tris: list, open_edges: list | None, seeds: list, surface: TileSurface | None = None
          ) -> np.ndarray:
    """(B, len(OWN_CUE_NAMES)) float32 cues of B pairs; seeds[b]: the subsampling seed of pair b; surface: the
    tile's faces, which every point -> mesh distance measures against (None: each pair's own faces)."""
    points = [np.asarray(p, np.float64).reshape(-1, 3) for p in points]
    tris = [np.asarray(t, np.float64).reshape(-1, 3, 3) for t in tris]
    n = np.array([len(p) for p in points], np.int64)
    m = np.array([len(t) for t in tris], np.int64)
    if (n == 0).any() or (m == 0).any():
        raise ValueError("every pair needs at least one point and one face")
    b = len(points)
    p_all, t = np.concatenate(points), np.concatenate(tris)
    ga, gf = np.repeat(np.arange(b), n), np.repeat(np.arange(b), m)
    f_start = np.concatenate([[0], np.cumsum(m)[:-1]])
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    area = 0.5 * area2
    normals = np.divide(cross, area2[:, None], out=np.zeros_like(cross), where=area2[:, None] > 0)
    centres = t.mean(axis=1)
    total_area = np.bincount(gf, area, minlength=b)

    p, gp, p_sh, gs = _cue_points(p_all, n, seeds)
    n_cue = np.bincount(gp, minlength=b)
    if surface is not None:  # the nearest surface anywhere in the tile, not only the pair's own faces
        d, off = surface.nearest(p)
        signed = np.sign(off) * d
    else:
        d, signed, off = _point_to_mesh(p, n_cue, t, m, normals, centres, 8)

    # mesh -> points, and the shape of the point set: on at most MAX_SHAPE_POINTS points per pair
    n_sh = np.bincount(gs, minlength=b)
    dm = nearest_distance_runs(p_sh, run_starts(n_sh), centres, run_starts(m))  # compiled grid search
    w = np.where((total_area > 0)[gf], area / np.where(total_area > 0, total_area, 1.0)[gf], 1.0 / m[gf])

    # boundaries: edges of the patch without a neighbour in the patch, and tile-level open edges
    nb = edge_neighbours(vertex_ids_from_coords(t.astype(np.float32)), gf)
    edge_len = np.linalg.norm(np.roll(t, -1, axis=1) - t, axis=2)  # (M, 3), edge j = v_j -> v_{j+1}
    patch_open = nb == np.arange(len(t))[:, None]
    tile_open = patch_open if open_edges is None else np.concatenate([np.asarray(o, bool).reshape(-1, 3)
                                                                      for o in open_edges])

    # normals and planarity
    mean_n = np.stack([np.bincount(gf, normals[:, i] * area, minlength=b) for i in range(3)], 1)
    mean_len = np.linalg.norm(mean_n, axis=1)
    mesh_n = np.where((mean_len > 0)[:, None], mean_n / np.where(mean_len > 0, mean_len, 1.0)[:, None], [0.0, 0.0, 1.0])
    pt_n, planarity = _point_normals(p_sh, n_sh, mesh_n)
    along_p = _dot(p_sh, mesh_n[gs])
    along_m = (t * mesh_n[gf][:, None]).sum(2).ravel()
    gv = np.repeat(gf, 3)

    def spread(v, g):
        s = sorted_segments(v, g, b)
        return percentile_of_sorted(s, 90) - percentile_of_sorted(s, 10)

    sd, ss, sm = sorted_segments(d, gp, b), sorted_segments(signed, gp, b), sorted_segments(dm, gf, b)
    cues = [
        np.log1p(n), np.log1p(m), total_area, np.log1p(n / np.maximum(total_area, 1e-3)),
        segment_mean(d, gp, n_cue), median_of_sorted(sd), percentile_of_sorted(sd, 90),
        segment_max(d, np.concatenate([[0], np.cumsum(n_cue)[:-1]])),
        segment_mean((d > 0.05).astype(float), gp, n_cue), segment_mean((d > 0.15).astype(float), gp, n_cue),
        median_of_sorted(ss), segment_mean(signed, gp, n_cue),
        segment_mean(dm, gf, m), percentile_of_sorted(sm, 90), segment_max(dm, f_start),
        np.bincount(gf, w * (dm <= 0.10), minlength=b),
        np.bincount(gf, (edge_len * patch_open).sum(1), minlength=b),
        np.bincount(gf, (edge_len * tile_open).sum(1), minlength=b),
        np.bincount(gf, tile_open.sum(1), minlength=b),
        np.abs((pt_n * mesh_n).sum(1)), planarity, 1.0 - mean_len / np.maximum(total_area, 1e-12),
        spread(along_p, gs), spread(along_m, gv),
        np.bincount(gf, w * (np.abs(normals[:, 2]) > 0.9), minlength=b),
    ] + _extra_cues(d, signed, gp, n_cue, sd, ss, sm, dm, gf, w, p_all[:, 2], ga, t[:, :, 2], b)
    cues += _surface_cues(d, off, gp, n_cue, b)
    return np.stack(cues, axis=1).astype(np.float32)


def _extra_cues(d, signed, gp, n_cue, sd, ss, sm, dm, gf, w, pz, ga, tz, b) -> list:
    """The :data:`EXTRA_CUE_NAMES` columns, (B,) float64 each: shares of points more than 10 cm behind / in
    front of the mesh and beyond 30 cm, quartiles of the point -> mesh distance, 10th / 90th percentiles of
    the signed distance, median mesh -> point distance and the area share of faces > 25 cm from every point,
    and how far the points reach above the mesh's top and below its bottom (m; z up). d, signed: (q,) per cue
    point of pair gp; sd, ss, sm: their and dm's :func:`sorted_segments`; dm, w: (M,) per face of pair gf;
    pz: (N,) z of all points of pair ga; tz: (M, 3) z of the faces' corners."""
    p_start = np.flatnonzero(np.r_[True, ga[1:] != ga[:-1]])  # ga: contiguous, ascending, every pair present
    zmax_p, zmin_p = np.maximum.reduceat(pz, p_start), np.minimum.reduceat(pz, p_start)
    zmax_m = np.full(b, -np.inf)
    zmin_m = np.full(b, np.inf)
    np.maximum.at(zmax_m, gf, tz.max(1))
    np.minimum.at(zmin_m, gf, tz.min(1))
    return [segment_mean((signed < -0.10).astype(float), gp, n_cue), segment_mean((signed > 0.10).astype(float), gp, n_cue),
            segment_mean((d > 0.30).astype(float), gp, n_cue), percentile_of_sorted(sd, 25), percentile_of_sorted(sd, 75),
            percentile_of_sorted(ss, 10), percentile_of_sorted(ss, 90), median_of_sorted(sm),
            np.bincount(gf, w * (dm > 0.25), minlength=b), zmax_p - zmax_m, zmin_m - zmin_p]


def pair_cues(points: np.ndarray, tris: np.ndarray, open_edges: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """(len(OWN_CUE_NAMES),) float32 cues of one pair (see :data:`OWN_CUE_NAMES`; the surface is its own faces).

    points: (n, 3) metres; tris: (m, 3, 3) metres (n, m >= 1); open_edges: (m, 3) bool tile-level open
    edges, or None (then the patch-local boundary stands in). Points beyond MAX_CUE_POINTS are subsampled
    (seeded by ``seed`` itself) for the point-to-mesh distances.
    """
    return _cues([points], [tris], None if open_edges is None else [open_edges], [seed])[0]


def batch_cues(points: list[np.ndarray], tris: list[np.ndarray], open_edges: list[np.ndarray] | None,
               keys: np.ndarray, seed: int = 0, surface: TileSurface | None = None) -> np.ndarray:
    """(B, len(OWN_CUE_NAMES)) float32 cues of B pairs, all pairs at once (one k-d tree per kind for the batch):
    the :data:`PAIR_CUE_NAMES` then the :data:`SURFACE_CUE_NAMES`.

    points[b]: (n_b, 3) float, metres; tris[b]: (m_b, 3, 3) float, metres (n_b, m_b >= 1); open_edges[b]:
    (m_b, 3) bool or None; keys: (B,) int64 patch keys (pair b subsamples with ``pair_seed(seed, keys[b])``);
    surface: the tile's faces (:class:`~ms3d_model.surface.TileSurface`) the surface cues measure against
    (None: each pair's own faces).

    >>> tris = np.array([[[0, 0, 0], [1, 0, 0], [1, 1, 0]], [[0, 0, 0], [1, 1, 0], [0, 1, 0]]], float)
    >>> pts = np.array([[.25, .5, .2], [.75, .5, .2], [.5, .25, .2], [.5, .75, .2]])  # 0.2 m above the square
    >>> c = dict(zip(PAIR_CUE_NAMES, batch_cues([pts, pts - [0, 0, .2]], [tris, tris], None, np.array([1, 2])).T))
    >>> [round(float(c[k][0]), 4) for k in ("p2m_median", "p2m_signed_mean", "mesh_area_m2", "patch_boundary_m")]
    [0.2, 0.2, 1.0, 4.0]
    >>> [round(float(c[k][1]), 4) for k in ("p2m_max", "coverage_10cm", "point_planarity")]
    [0.0, 0.0, 0.0]
    """
    n = [len(p) for p in points]
    return _cues(points, tris, open_edges, _group_seeds(n, np.asarray(keys, np.int64), seed), surface)
