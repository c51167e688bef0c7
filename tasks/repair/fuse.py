"""Graph-cut fusion of mesh vertices and MLS points (Liu et al. 2023, §5.1).

The mesh vertices are the reference and the MLS points the candidates. Every vertex and every
point is a node of one graph with a binary label: ``L`` (the MLS is the source of the surface here)
or ``M`` (the mesh is). A vertex labelled L is *replaced* (dropped from the fused set), a point
labelled L is *accepted* (kept in it). The energy

    E(l) = sum_v D_v(l_v) + sum_p D_p(l_p) + sum_{(i,j) in kNN} w_ij [l_i != l_j]

is minimised exactly by an s-t min-cut (:func:`tasks.repair.mincut.min_cut`): binary labels with a Potts
smoothness term are submodular. The terms:

- similarity of a vertex v and a point p: ``s = exp(-d²/2σd² - θ²/2σθ²)`` with d the Euclidean
  distance and θ the angle between their (unsigned) normals; ``s_v`` is the best over the points
  within ``search_radius_m``. ``D_v(L) = w (τ - s_v)+ / τ`` and ``D_v(M) = w (s_v - τ)+ / (1 - τ)``:
  without smoothness a vertex is replaced exactly when its similarity exceeds the threshold τ.
  A vertex with no MLS near it (roofs, occluded parts) has s_v = 0 and stays: completeness from the
  mesh, accuracy from the MLS.
- a point p is *compatible* when its offset along the nearest vertex's normal lies in
  ``[-point_depth_m, +point_reach_m]`` (the wall behind a protrusion is compatible, a fence 1 m in
  front of the facade is not). Compatible points similar to a vertex (s_p > τ) strongly prefer L,
  other compatible points weakly prefer L (they *supplement* the mesh, e.g. inside a hole), and
  incompatible ones strongly prefer M (rejected).
- ``w_ij = λ exp(-d_ij²/2σd²)`` over the symmetric k-NN graph of all nodes: neighbouring nodes
  agree, so the points around a matched point are accepted with it and a vertex surrounded by
  replaced vertices follows them.
- typed repair (``forced``): vertices that the MLS surface covers but that lie in front of it
  (protrusion) or behind it (recess) get a hard L (see :func:`coverage_offsets`).

Worked example (the test's case): a plane of vertices 10 cm above an accurate MLS plane that covers
half of it -> exactly the covered vertices are replaced.

Frames and units: campus-local metres; normals unit length.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ms3d_model.kernels import knn_pca, nearest_to_centroid
from tasks.repair.mincut import min_cut

_BIG = 1e6


@dataclass(frozen=True)
class FusionParams:
    """See :class:`tasks.config.repair.FusionConfig` for meanings and where the defaults come from."""

    sigma_distance_m: float = 0.06
    sigma_angle_deg: float = 25.0
    similarity_threshold: float = 0.25
    search_radius_m: float = 0.25
    point_reach_m: float = 0.6
    point_depth_m: float = 1.2
    k_neighbours: int = 8
    smoothness: float = 0.6
    unary_weight: float = 4.0

    @classmethod
    def from_config(cls, c) -> FusionParams:
        return cls(**{k: getattr(c, k) for k in cls.__dataclass_fields__})


@dataclass(frozen=True)
class FusionResult:
    """replaced: (nv,) bool mesh vertices dropped; accepted: (np,) bool MLS points kept;
    vertex_similarity: (nv,) float best similarity to the MLS; point_similarity: (np,) best similarity
    to the mesh; compatible: (np,) bool; energy: the minimised energy; flow: the max-flow value."""

    replaced: np.ndarray
    accepted: np.ndarray
    vertex_similarity: np.ndarray
    point_similarity: np.ndarray
    compatible: np.ndarray
    energy: float
    flow: float

    def fused(self, mesh_xyz: np.ndarray, mls_xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """((k, 3) fused points, (k,) int8 source: 0 mesh vertex, 1 MLS point)."""
        kept, acc = mesh_xyz[~self.replaced], mls_xyz[self.accepted]
        return np.concatenate([kept, acc]), np.r_[np.zeros(len(kept), np.int8), np.ones(len(acc), np.int8)]


# ------------------------------------------------------------------------------------- normals

def pca_normals(xyz: np.ndarray, k: int = 12, tree: cKDTree | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Unoriented PCA normals and planarity of points.

    xyz: (n, 3) float metres. Returns ((n, 3) float64 unit normals, (n,) float64 surface variation
    λ0 / (λ0 + λ1 + λ2) in [0, 1/3], small on planes).
    """
    xyz = np.asarray(xyz, np.float64)
    n = len(xyz)
    if n < 3:
        return np.tile([0.0, 0.0, 1.0], (n, 1)), np.zeros(n)
    k = min(k, n)
    tree = tree or cKDTree(xyz)
    _, idx = tree.query(xyz, k=k)
    return knn_pca(xyz, np.asarray(idx, np.int64).reshape(n, k))  # compiled: no (n, k, 3) gather, no LAPACK


def orient_like(normals: np.ndarray, xyz: np.ndarray, ref_xyz: np.ndarray, ref_normals: np.ndarray) -> np.ndarray:
    """Flip each normal to agree with the nearest reference normal (e.g. the mesh's outward normals)."""
    if len(ref_xyz) == 0 or len(xyz) == 0:
        return normals
    _, j = cKDTree(ref_xyz).query(xyz)
    flip = np.einsum("ij,ij->i", normals, ref_normals[j]) < 0
    out = normals.copy()
    out[flip] *= -1
    return out


def thin_points(xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of one point per voxel (the one nearest its voxel's centroid, the first row on a tie),
    sorted. xyz: (n, 3).

    One stable sort of the voxel keys serves the grouping and the choice (real MLS density: millions of
    points per region).

    >>> thin_points(np.array([[0.0, 0, 0], [0.04, 0, 0], [0.02, 0, 0], [0.5, 0, 0]]), 0.1).tolist()
    [2, 3]
    """
    n = len(xyz)
    if n == 0:
        return np.zeros(0, np.int64)
    xyz = np.asarray(xyz, np.float64)
    cell = np.floor(xyz / voxel_m).astype(np.int64)
    cell -= cell.min(axis=0)
    if (cell.max(axis=0) < (1 << 21)).all():  # one int64 key per voxel, ordered like the rows (x, y, z)
        order = np.argsort((cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2], kind="stable")
    else:
        order = np.lexsort((cell[:, 2], cell[:, 1], cell[:, 0]))
    cs = cell[order]
    starts = np.flatnonzero(np.r_[True, (cs[1:] != cs[:-1]).any(axis=1)])
    return np.sort(nearest_to_centroid(xyz, order.astype(np.int64), starts))  # rows ascend within a voxel


# ------------------------------------------------------------------------------------- similarity

def similarity(d: np.ndarray, cos_abs: np.ndarray, p: FusionParams) -> np.ndarray:
    """exp(-d²/2σd² - θ²/2σθ²) with θ = arccos|cos|: (k,) metres, (k,) -> (k,) in [0, 1]."""
    theta = np.degrees(np.arccos(np.clip(cos_abs, 0.0, 1.0)))
    return np.exp(-0.5 * (d / p.sigma_distance_m) ** 2 - 0.5 * (theta / p.sigma_angle_deg) ** 2)


def best_similarity(a_xyz, a_n, b_xyz, b_n, b_tree: cKDTree, p: FusionParams, k: int = 8) -> np.ndarray:
    """For each point of a, the best similarity to its k nearest points of b within the search radius."""
    if len(a_xyz) == 0 or len(b_xyz) == 0:
        return np.zeros(len(a_xyz))
    k = min(k, len(b_xyz))
    d, j = b_tree.query(a_xyz, k=k, distance_upper_bound=p.search_radius_m)
    d, j = d.reshape(len(a_xyz), k), j.reshape(len(a_xyz), k)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    cos = np.abs(np.einsum("nd,nkd->nk", a_n, b_n[jj]))
    s = np.where(ok, similarity(np.where(ok, d, 0.0), cos, p), 0.0)
    return s.max(axis=1)


def coverage_offsets(mesh_xyz, mls_xyz, mls_n, mls_tree: cKDTree, max_depth_m: float,
                     lateral_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Where the MLS surface covers each mesh vertex, and the vertex's offset from it.

    For each vertex v, the nearest MLS point p (within max_depth_m) gives the offset
    o = (v - p) . n_p (positive: v lies in front of the MLS surface, on the normal's side) and the
    lateral distance |(v - p) - o n_p|. Covered: lateral <= lateral_m (the foot of the perpendicular
    lies on scanned surface). Returns ((nv,) bool covered, (nv,) float offset, NaN where uncovered).
    """
    if len(mls_xyz) == 0 or len(mesh_xyz) == 0:
        return np.zeros(len(mesh_xyz), bool), np.full(len(mesh_xyz), np.nan)
    d, j = mls_tree.query(mesh_xyz, distance_upper_bound=max_depth_m)
    ok = np.isfinite(d)
    jj = np.where(ok, j, 0)
    delta = mesh_xyz - mls_xyz[jj]
    off = np.einsum("ij,ij->i", delta, mls_n[jj])
    lat = np.linalg.norm(delta - off[:, None] * mls_n[jj], axis=1)
    covered = ok & (lat <= lateral_m)
    return covered, np.where(covered, off, np.nan)


# ------------------------------------------------------------------------------------- graph cut

def _knn_edges(xyz: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Symmetric k-NN edges (i < j, unique) and their lengths."""
    n = len(xyz)
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    k = min(k + 1, n)
    d, j = cKDTree(xyz).query(xyz, k=k)
    i = np.repeat(np.arange(n), k - 1)
    j, d = j[:, 1:].ravel(), d[:, 1:].ravel()
    a, b = np.minimum(i, j), np.maximum(i, j)
    key = a * n + b
    _, first = np.unique(key, return_index=True)
    return a[first], b[first], d[first]


def graph_cut_fuse(mesh_xyz: np.ndarray, mesh_n: np.ndarray, mls_xyz: np.ndarray, mls_n: np.ndarray,
                   params: FusionParams = FusionParams(), forced: np.ndarray | None = None,
                   locked: np.ndarray | None = None, mls_tree: cKDTree | None = None) -> FusionResult:
    """Decide which mesh vertices the MLS replaces and which MLS points join them (§5.1).

    mesh_xyz, mesh_n: (nv, 3) float vertex positions and unit normals (outward);
    mls_xyz, mls_n: (np, 3) float MLS points and unit normals (oriented like the mesh's);
    forced: optional (nv,) bool vertices that must be replaced (typed repair: protrusion, recess);
    locked: optional (nv,) bool vertices that must stay (e.g. the region's border ring);
    mls_tree: the k-d tree of mls_xyz when the caller has it (else built here).
    Returns a :class:`FusionResult`.
    """
    p = params
    mv, mp = np.asarray(mesh_xyz, np.float64), np.asarray(mls_xyz, np.float64)
    nv, npt = len(mv), len(mp)
    tau, w = p.similarity_threshold, p.unary_weight
    mls_tree = (mls_tree if mls_tree is not None else cKDTree(mp)) if npt else None
    mesh_tree = cKDTree(mv) if nv else None
    s_v = best_similarity(mv, mesh_n, mp, mls_n, mls_tree, p) if npt else np.zeros(nv)
    s_p = best_similarity(mp, mls_n, mv, mesh_n, mesh_tree, p) if nv else np.zeros(npt)
    compatible = np.ones(npt, bool)
    if nv and npt:
        reach = p.point_depth_m + p.point_reach_m
        d, j = mesh_tree.query(mp, distance_upper_bound=3.0 * reach)
        ok = np.isfinite(d)
        jj = np.where(ok, j, 0)
        off = np.einsum("ij,ij->i", mp - mv[jj], mesh_n[jj])
        compatible = ok & (off <= p.point_reach_m) & (off >= -p.point_depth_m)
    # unaries: source side = L (MLS), sink side = M (mesh). A node on the sink side pays its source capacity,
    # on the source side its sink capacity. So cap_source = D(M), cap_sink = D(L).
    dv_l = w * np.clip(tau - s_v, 0, None) / tau
    dv_m = w * np.clip(s_v - tau, 0, None) / (1 - tau)
    if forced is not None:
        dv_m = np.where(forced, _BIG, dv_m)
        dv_l = np.where(forced, 0.0, dv_l)
    if locked is not None:
        dv_l = np.where(locked, _BIG, dv_l)
        dv_m = np.where(locked, 0.0, dv_m)
    dp_l = np.where(compatible, 0.0, 10.0 * w)
    dp_m = np.where(compatible, np.where(s_p > tau, w, 0.25 * w), 0.0)
    n = nv + npt
    cap_src = np.r_[dv_m, dp_m]
    cap_snk = np.r_[dv_l, dp_l]
    allxyz = np.concatenate([mv, mp]) if n else np.zeros((0, 3))
    a, b, d = _knn_edges(allxyz, p.k_neighbours)
    wij = p.smoothness * np.exp(-0.5 * (d / p.sigma_distance_m) ** 2)
    keep = wij > 1e-9
    a, b, wij = a[keep], b[keep], wij[keep]
    flow, sink = min_cut(cap_src, cap_snk, a, b, wij, wij)
    label_l = ~sink  # source side
    energy = float(np.where(label_l, cap_snk, cap_src).sum() + wij[label_l[a] != label_l[b]].sum())
    return FusionResult(replaced=label_l[:nv], accepted=label_l[nv:], vertex_similarity=s_v,
                        point_similarity=s_p, compatible=compatible, energy=energy, flow=float(flow))
