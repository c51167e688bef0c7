"""Hand-made geometric cues of a (mesh patch, point patch) pair: the non-deep baseline's features and the
extra input of MS3DQE-Net+.

All in metres, from the raw (unsampled) patch: how far the MLS points lie from the mesh and the mesh from
the points (both ways), how much of the mesh the MLS covers, open (boundary) edges, normal agreement,
planarity, counts. In the spirit of Ennafii et al. (PE&RS 2019): cheap, interpretable, and the honest bar a
network has to clear.

``open_edges`` (per face, per edge) says whether the edge has no other face in the whole tile (a real
mesh boundary: a hole), as opposed to the patch's own cut; a face whose neighbour lies in the next tile
counts as open too (rare: only along tile borders).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .features import edge_neighbours, pair_seed, vertex_ids_from_coords

CUE_NAMES = (
    "log_n_points", "log_n_faces", "mesh_area_m2", "log_point_density",
    "p2m_mean", "p2m_median", "p2m_p90", "p2m_max", "p2m_frac_5cm", "p2m_frac_15cm",
    "p2m_signed_median", "p2m_signed_mean",
    "m2p_mean", "m2p_p90", "m2p_max", "coverage_10cm",
    "patch_boundary_m", "open_edge_m", "open_edge_count",
    "normal_agreement", "point_planarity", "mesh_normal_spread",
    "point_spread_along_normal", "mesh_spread_along_normal", "frac_horizontal_faces",
)
N_CUES = len(CUE_NAMES)
MAX_CUE_POINTS = 1024


def closest_point_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Closest points on triangles, row by row (Ericson, Real-Time Collision Detection §5.1.5, vectorised).

    p: (q, 3) float64 points; tri: (q, 3, 3) float64 triangles. Returns (q, 3) float64.

    >>> t = np.array([[[0., 0, 0], [1, 0, 0], [0, 1, 0]]] * 3)
    >>> closest_point_on_triangles(np.array([[.2, .2, 1], [2, 2, 0], [-1, -1, 0]]), t).round(6).tolist()
    [[0.2, 0.2, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 0.0]]
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(1), (ac * ap).sum(1)
    bp = p - b
    d3, d4 = (ab * bp).sum(1), (ac * bp).sum(1)
    cp = p - c
    d5, d6 = (ab * cp).sum(1), (ac * cp).sum(1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        v = np.where(denom != 0, vb / denom, 0.0)
        w = np.where(denom != 0, vc / denom, 0.0)
        out = a + ab * v[:, None] + ac * w[:, None]  # interior
        # Ericson's tests in reverse order (a later np.where wins): edge bc, edge ac, vertex c, edge ab, b, a
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        m = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
        out = np.where(m[:, None], b + (c - b) * t_bc[:, None], out)
        t_ac = d2 / (d2 - d6)
        m = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
        out = np.where(m[:, None], a + ac * t_ac[:, None], out)
        out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)  # vertex c
        t_ab = d1 / (d1 - d3)
        m = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
        out = np.where(m[:, None], a + ab * t_ab[:, None], out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)  # vertex b
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)  # vertex a
    return out


def open_edge_flags(vids: np.ndarray) -> np.ndarray:
    """(m, 3) bool: edge (v_j, v_{j+1}) of each face is used by no other face of ``vids`` (m, 3) int64."""
    return edge_neighbours(vids) == np.arange(len(vids))[:, None]


def pair_cues(points: np.ndarray, tris: np.ndarray, open_edges: np.ndarray | None = None, seed: int = 0) -> np.ndarray:
    """(N_CUES,) float32 cues of one pair (see :data:`CUE_NAMES`).

    points: (n, 3) metres; tris: (m, 3, 3) metres (n, m >= 1); open_edges: (m, 3) bool tile-level open
    edges, or None (then the patch-local boundary stands in). Points beyond MAX_CUE_POINTS are subsampled
    (seeded) for the point-to-mesh distances.
    """
    p_all = np.asarray(points, np.float64).reshape(-1, 3)
    t = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    n, m = len(p_all), len(t)
    rng = np.random.default_rng(seed)
    p = p_all[rng.choice(n, MAX_CUE_POINTS, replace=False)] if n > MAX_CUE_POINTS else p_all
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    area = 0.5 * area2
    normals = np.divide(cross, area2[:, None], out=np.zeros_like(cross), where=area2[:, None] > 0)
    centres = t.mean(axis=1)
    total_area = float(area.sum())

    # point -> mesh: exact distance to the nearest of the k faces with the nearest centres
    k = min(8, m)
    _, fi = cKDTree(centres).query(p, k=k)
    fi = np.asarray(fi).reshape(len(p), k)
    q = closest_point_on_triangles(np.repeat(p, k, axis=0), t[fi.ravel()]).reshape(len(p), k, 3)
    dist = np.linalg.norm(q - p[:, None], axis=2)
    best = dist.argmin(axis=1)
    d = dist[np.arange(len(p)), best]
    fbest = fi[np.arange(len(p)), best]
    signed = np.sign(((p - q[np.arange(len(p)), best]) * normals[fbest]).sum(1)) * d

    # mesh -> points
    dm, _ = cKDTree(p_all).query(centres, k=1)
    w = area / total_area if total_area > 0 else np.full(m, 1.0 / m)

    # boundaries: edges of the patch without a neighbour in the patch, and tile-level open edges
    nb = edge_neighbours(vertex_ids_from_coords(t.astype(np.float32)))
    edge_len = np.linalg.norm(np.roll(t, -1, axis=1) - t, axis=2)  # (m, 3), edge j = v_j -> v_{j+1}
    patch_open = nb == np.arange(m)[:, None]
    tile_open = patch_open if open_edges is None else np.asarray(open_edges, bool)

    # normals and planarity
    mean_n = (normals * area[:, None]).sum(0)
    mean_len = np.linalg.norm(mean_n)
    mesh_n = mean_n / mean_len if mean_len > 0 else np.array([0.0, 0.0, 1.0])
    if n >= 3:
        ev, evec = np.linalg.eigh(np.cov(p_all.T))
        pt_n = evec[:, 0]
        planarity = float(max(ev[0], 0.0) / max(ev.sum(), 1e-12))
    else:
        pt_n, planarity = mesh_n, 0.0
    along_p = p_all @ mesh_n
    along_m = t.reshape(-1, 3) @ mesh_n

    cues = [
        np.log1p(n), np.log1p(m), total_area, np.log1p(n / max(total_area, 1e-3)),
        d.mean(), np.median(d), np.percentile(d, 90), d.max(), (d > 0.05).mean(), (d > 0.15).mean(),
        np.median(signed), signed.mean(),
        dm.mean(), np.percentile(dm, 90), dm.max(), float(w[dm <= 0.10].sum()),
        float(edge_len[patch_open].sum()), float(edge_len[tile_open].sum()), float(tile_open.sum()),
        abs(float(pt_n @ mesh_n)), planarity, 1.0 - mean_len / max(total_area, 1e-12),
        np.percentile(along_p, 90) - np.percentile(along_p, 10), np.percentile(along_m, 90) - np.percentile(along_m, 10),
        float(w[np.abs(normals[:, 2]) > 0.9].sum()),
    ]
    return np.asarray(cues, np.float32)


def batch_cues(points: list[np.ndarray], tris: list[np.ndarray], open_edges: list[np.ndarray] | None,
               keys: np.ndarray, seed: int = 0) -> np.ndarray:
    """(B, N_CUES) float32 cues of B pairs (one :func:`pair_cues` per pair; vectorised within each pair)."""
    out = np.empty((len(points), N_CUES), np.float32)
    for b in range(len(points)):
        oe = None if open_edges is None else open_edges[b]
        out[b] = pair_cues(points[b], tris[b], oe, pair_seed(seed, int(keys[b])))
    return out
