"""Triangulation of a region's fused points, clipped to the region and stitched to the retained mesh (§5.2).

Two methods, both ending in the region's charts (:mod:`tasks.repair.chart`), so both weld exactly to
the retained border by vertex id:

- ``delaunay`` (default, chosen by measured accuracy: docs/repair.md): the fused points themselves
  are triangulated, Delaunay in the chart's disc coordinates, an interpolating surface in the spirit
  of the paper's Gopi et al. (2000), whose lower-dimensional localized Delaunay triangulation
  projects neighbourhoods onto tangent planes; here the projection is one global map per chart.
- ``poisson``: screened Poisson reconstruction (open3d) of the fused points with their normals,
  trimmed by density, cropped to the region; its vertices are then triangulated in the chart the
  same way (the Poisson surface gives the geometry, the chart the connectivity and the weld).

Clipping: only fused points that land inside a chart (closest point on the zone surface, within
``max_map_distance_m``, not on its border) are used, so the rebuilt surface covers exactly the
replaced faces plus their filled holes. Stitching: the chart boundary vertices are the retained
border's own vertices, kept with their ids; the Delaunay hull is the border polygon, so every border
edge is a rebuilt edge. :func:`border_gap` measures what is left (0 where welded).

Frames and units: campus-local metres, float64 inside, float32 out.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import Delaunay, cKDTree

from storage.vertex_ids import local_ids
from tasks.repair.chart import Chart, boundary_edges, edges_of, undirected_key
from tasks.repair.conformal import constrained_triangles
from tasks.repair.standing import standing_in_charts

METHODS = ("delaunay", "poisson")


@dataclass(frozen=True)
class RebuiltMesh:
    """A region's rebuilt surface.

    xyz: (n, 3) float64 campus-local metres; vertex_id: (n,) int64 (a campus id, :mod:`storage.vertex_ids`:
    the original mesh vertex, welded to the retained mesh or kept in place; a local id: a new vertex,
    unique within the region);
    faces: (m, 3) int64; source: (n,) int8 (0 original mesh vertex, 1 MLS point, 2 Poisson vertex, 3 sample of
    the input surface where the MLS saw nothing: tasks.repair.fill);
    chart: (m,) int32 chart index of each face.
    """

    xyz: np.ndarray
    vertex_id: np.ndarray
    faces: np.ndarray
    source: np.ndarray
    chart: np.ndarray
    stats: dict = field(default_factory=dict)

    @property
    def n_faces(self) -> int:
        return len(self.faces)


def empty_mesh() -> RebuiltMesh:
    return RebuiltMesh(np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros(0, np.int8),
                       np.zeros(0, np.int32), {})


# ------------------------------------------------------------------------------------- geometry kernels

class ClosestPoint:
    """Closest points on a triangle set (open3d's RaycastingScene, float32 around a local centre)."""

    def __init__(self, xyz: np.ndarray, faces: np.ndarray):
        import open3d as o3d

        self.centre = np.asarray(xyz, np.float64).mean(axis=0) if len(xyz) else np.zeros(3)
        self.scene = o3d.t.geometry.RaycastingScene()
        self.n = len(faces)
        if self.n:
            self.scene.add_triangles((np.asarray(xyz, np.float64) - self.centre).astype(np.float32),
                                     np.asarray(faces, np.uint32))

    def query(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """pts (k, 3) -> ((k,) face id, (k, 3) barycentric weights of the face's corners, (k,) distance)."""
        if self.n == 0 or len(pts) == 0:
            return np.full(len(pts), -1), np.zeros((len(pts), 3)), np.full(len(pts), np.inf)
        q = (np.asarray(pts, np.float64) - self.centre).astype(np.float32)
        r = self.scene.compute_closest_points(q)
        fid = r["primitive_ids"].numpy().astype(np.int64)
        uv = r["primitive_uvs"].numpy().astype(np.float64)
        bary = np.c_[1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]]
        d = np.linalg.norm(r["points"].numpy().astype(np.float64) - q, axis=1)
        return fid, bary, d


def _segment_samples(xyz: np.ndarray, edges: np.ndarray, step: float) -> np.ndarray:
    """Points every ``step`` metres along each edge (end points included)."""
    if len(edges) == 0:
        return np.zeros((0, 3))
    a, b = xyz[edges[:, 0]], xyz[edges[:, 1]]
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step).astype(np.int64), 1)
    e = np.repeat(np.arange(len(edges)), n + 1)
    t = (np.arange(len(e)) - np.repeat(np.cumsum(n + 1) - (n + 1), n + 1)) / np.repeat(n, n + 1)
    return a[e] + t[:, None] * (b[e] - a[e])


def _inside_convex_ccw(poly: np.ndarray, pts: np.ndarray, eps: float) -> np.ndarray:
    """Points strictly inside a counter-clockwise convex polygon, by at least eps from every edge line."""
    inside = np.ones(len(pts), bool)
    nxt = np.roll(poly, -1, axis=0)
    for a, b in zip(poly, nxt):  # one vectorised test per edge; polygons have at most a few thousand edges
        d = b - a
        ln = np.hypot(*d)
        if ln <= 0:
            continue
        cross = (d[0] * (pts[:, 1] - a[1]) - d[1] * (pts[:, 0] - a[0])) / ln
        inside &= cross > eps
    return inside


def _inside_polygon(poly: np.ndarray, pts: np.ndarray, eps: float) -> np.ndarray:
    """Points inside a simple polygon (even-odd rule) and farther than eps from each of its edges.

    Each edge is tested only against the points in its band of v (the points sorted by v once): a point
    outside ``[v_min, v_max)`` cannot cross the edge's ray, nor lie within eps of it outside the band
    grown by 2 eps, so the result equals testing every point against every edge, in O(P log P + band)."""
    order = np.argsort(pts[:, 1], kind="stable")
    sp = pts[order]
    ys = sp[:, 1]
    inside = np.zeros(len(pts), bool)
    clear = np.ones(len(pts), bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        lo, hi = (a[1], b[1]) if a[1] <= b[1] else (b[1], a[1])
        i0, i1 = np.searchsorted(ys, [lo, hi])  # (a_v > v) != (b_v > v)  <=>  lo <= v < hi
        q = sp[i0:i1]
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = a[0] + (q[:, 1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
        inside[i0:i1] ^= q[:, 0] < xc
        j0 = int(np.searchsorted(ys, lo - 2 * eps, side="left"))
        j1 = int(np.searchsorted(ys, hi + 2 * eps, side="right"))
        q = sp[j0:j1]
        d = b - a
        t = np.clip(((q - a) @ d) / max(float(d @ d), 1e-30), 0.0, 1.0)
        clear[j0:j1] &= np.linalg.norm(q - (a + t[:, None] * d), axis=1) > eps
    out = np.empty(len(pts), bool)
    out[order] = inside & clear
    return out


def _disc_points(buv: np.ndarray, bxyz: np.ndarray, puv: np.ndarray, keep: np.ndarray, pts: np.ndarray,
                 loop: np.ndarray, conformal: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The kept points inside the boundary polygon (buv: convex disc, or the conformal polygon), joined to
    the boundary: (kidx point indices, uv (q, 2), xyz (q, 3), index (q,) as triangulate_in_chart returns)."""
    inside = np.zeros(0, bool)
    if keep.any():
        inside = _inside_polygon(buv, puv[keep], 1e-6) if conformal else _inside_convex_ccw(buv, puv[keep], 1e-9)
    kidx = np.flatnonzero(keep)[inside]
    uv_all = np.concatenate([buv, puv[kidx]])
    xyz_all = np.concatenate([bxyz, pts[kidx]])
    index = np.r_[loop, -(1 + kidx)]
    # a triangulation of exactly coincident points would drop one: keep the first of each
    _, first = np.unique(np.round(uv_all, 12), axis=0, return_index=True)
    if len(first) < len(uv_all):
        sel = np.union1d(np.sort(first), np.arange(len(loop)))
        uv_all, xyz_all, index = uv_all[sel], xyz_all[sel], index[sel]
    return kidx, uv_all, xyz_all, index


def _disc_delaunay(uv: np.ndarray) -> np.ndarray:
    """Delaunay triangles (t, 3) int64 of points in the unit disc whose hull is the boundary polygon."""
    return Delaunay(uv).simplices.astype(np.int64)


# ------------------------------------------------------------------------------------- surface methods

def poisson_surface(xyz: np.ndarray, normals: np.ndarray, depth: int = 8, trim_quantile: float = 0.05,
                    threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screened Poisson (open3d) of oriented points, density-trimmed.

    xyz, normals: (n, 3) float64. Returns ((v, 3) float64 vertices, (f, 3) int64 faces, (v, 3) unit
    vertex normals) with the vertices of density below the ``trim_quantile`` quantile removed.
    """
    import open3d as o3d

    if len(xyz) < 10:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    c = xyz.mean(axis=0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz - c))
    pcd.normals = o3d.utility.Vector3dVector(normals)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, dens = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
            pcd, depth=depth, scale=1.1, linear_fit=False, n_threads=threads)
    dens = np.asarray(dens)
    if trim_quantile > 0 and len(dens):
        mesh.remove_vertices_by_mask(dens < np.quantile(dens, trim_quantile))
    mesh.compute_vertex_normals()
    return (np.asarray(mesh.vertices) + c, np.asarray(mesh.triangles, np.int64), np.asarray(mesh.vertex_normals))


def poisson_depth_for(extent_m: float, spacing_m: float, lo: int = 5, hi: int = 12) -> int:
    """Octree depth whose finest cell is about ``spacing_m`` over a cube of side ``extent_m`` x 1.1."""
    return int(np.clip(np.ceil(np.log2(max(extent_m * 1.1, spacing_m) / spacing_m)), lo, hi))


# ------------------------------------------------------------------------------------- chart triangulation

def triangulate_in_chart(chart: Chart, pts: np.ndarray, *, max_map_distance_m: float, border_margin_m: float,
                         max_edge_m: float, located: tuple | None = None,
                         vertex_xyz: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Delaunay triangulation of points in a chart, with the chart's boundary vertices fixed.

    chart: a disc of the zone (boundary = retained border + mesh edge); pts: (k, 3) float64 candidate
    points (fused points, or Poisson vertices). Points farther than max_map_distance_m from the chart
    surface, or whose closest point lies within border_margin_m of the chart boundary, are dropped.
    located: the chart's ``ClosestPoint.query(pts)`` when already computed. vertex_xyz: output positions
    of the region's vertices (chart.vertex indexes it; default: the chart's own positions), e.g. seam
    vertices moved onto the MLS surface.
    Returns (xyz (q, 3) of the triangulated points = boundary vertices first, then kept points;
    index (q,) int64: the chart vertex (>= 0, boundary) or -(1 + point index) for a point;
    faces (t, 3) int64 into xyz, counter-clockwise in the disc = oriented like the zone; stats).
    """
    loop = chart.loop
    bxyz = chart.xyz[loop].copy()
    if vertex_xyz is not None:
        own = chart.vertex[loop] >= 0
        bxyz[own] = vertex_xyz[chart.vertex[loop][own]]
    stats = {"candidates": len(pts)}
    keep = np.zeros(len(pts), bool)
    puv = np.zeros((len(pts), 2))
    fid, bary = np.zeros(len(pts), np.int64), np.zeros((len(pts), 3))
    if len(pts):
        fid, bary, dist = located if located is not None else ClosestPoint(chart.xyz, chart.faces).query(pts)
        ok = (fid >= 0) & (dist <= max_map_distance_m)
        foot = np.einsum("kc,kcd->kd", bary, chart.xyz[chart.faces[np.maximum(fid, 0)]])
        loop_edges = np.c_[loop, np.roll(loop, -1)]
        samples = _segment_samples(chart.xyz, loop_edges, max(border_margin_m / 2, 1e-3))
        near_border = cKDTree(samples).query(foot, distance_upper_bound=border_margin_m)[0] < np.inf
        keep = ok & ~near_border
        stats["too_far"] = int((~ok).sum())
        stats["at_border"] = int((ok & near_border).sum())
    kidx, uv_all, xyz_all, index, tri = None, None, None, None, None
    for cmap in ([chart.cuv] if chart.cuv is not None else []) + [chart.uv]:
        conformal = cmap is not chart.uv
        puv = np.einsum("kc,kcd->kd", bary, cmap[chart.faces[np.maximum(fid, 0)]]) if len(pts) else puv
        kidx, uv_all, xyz_all, index = _disc_points(cmap[loop], bxyz, puv, keep, pts, loop, conformal)
        if len(uv_all) < 3:
            return xyz_all, index, np.zeros((0, 3), np.int64), stats
        tri = constrained_triangles(uv_all, len(loop)) if conformal else _disc_delaunay(uv_all)
        if tri is not None:
            stats["conformal"] = int(conformal)
            break
    a, b, c = (uv_all[tri[:, k]] for k in range(3))
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    tri = np.where((cross < 0)[:, None], tri[:, [0, 2, 1]], tri)
    tri = tri[np.abs(cross) > 0]
    e = xyz_all[tri]
    longest = np.max(np.linalg.norm(e - np.roll(e, -1, axis=1), axis=2), axis=1)
    on_border = (tri < len(loop)).sum(1) >= 2  # a face on the border keeps the weld whatever its shape
    drop = (longest > max_edge_m) & ~on_border
    if drop.any():  # a long face is a fold only when it stands across the chart surface under it
        n = np.cross(e[drop, 1] - e[drop, 0], e[drop, 2] - e[drop, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1), 1e-18)[:, None]
        fid, _, _ = ClosestPoint(chart.xyz, chart.faces).query(e[drop].mean(axis=1))
        cf = chart.xyz[chart.faces[np.maximum(fid, 0)]]
        cn = np.cross(cf[:, 1] - cf[:, 0], cf[:, 2] - cf[:, 0])
        cn /= np.maximum(np.linalg.norm(cn, axis=1), 1e-18)[:, None]
        idx = np.flatnonzero(drop)
        drop[idx[np.einsum("ij,ij->i", n, cn) > 0.5]] = False
    stats["dropped_long"] = int(drop.sum())
    stats["used_points"] = len(kidx)
    return xyz_all, index, tri[~drop], stats


def rebuild_charts(charts: list[Chart], vertex_ids: np.ndarray, pts: np.ndarray, pts_source: np.ndarray,
                   pts_vertex: np.ndarray, *, max_map_distance_m: float, border_margin_m: float,
                   max_edge_m: float, vertex_xyz: np.ndarray | None = None, pts_normal: np.ndarray | None = None,
                   stand_off_m: float = 0.0) -> RebuiltMesh:
    """Triangulate the points in every chart and join the charts into one mesh, welded by vertex id.

    vertex_ids: (n,) int64 ids of the region's vertex table (chart.vertex indexes it);
    pts: (k, 3) points to triangulate; pts_source: (k,) int8 (0 mesh vertex, 1 MLS, 2 Poisson);
    pts_vertex: (k,) int64 region vertex index of a point that is an original mesh vertex, else -1;
    vertex_xyz: (n, 3) output positions of the region's vertices (default: as in the charts);
    pts_normal: (k, 3) unit normals of pts: with stand_off_m > 0, the MLS points standing on an up-facing
    stretch of their chart more than stand_off_m above it are left out (:mod:`tasks.repair.standing`).
    """
    xs, ids, fs, srcs, chs = [], [], [], [], []
    stats = {"charts": len(charts), "dropped_long": 0, "at_border": 0, "too_far": 0, "standing": 0}
    base = 0
    owner, located = _locate_in_charts(charts, pts)
    if pts_normal is not None and stand_off_m > 0 and len(pts):
        owner = np.where(standing_in_charts(charts, located, owner, pts, pts_normal, pts_source, stand_off_m),
                         -1, owner)
        stats["standing"] = int((owner < 0).sum())
    for ci, ch in enumerate(charts):
        mine = np.flatnonzero(owner == ci)  # each point goes to the chart nearest to it
        q = tuple(a[mine] for a in located[ci])
        xyz, index, tri, st = triangulate_in_chart(ch, pts[mine], max_map_distance_m=max_map_distance_m,
                                                   border_margin_m=border_margin_m, max_edge_m=max_edge_m,
                                                   located=q, vertex_xyz=vertex_xyz)
        index = np.where(index >= 0, index, -1 - np.r_[mine, 0][np.maximum(-1 - index, 0)])
        for k in ("dropped_long", "at_border", "too_far"):
            stats[k] += st.get(k, 0)
        is_b = index >= 0
        pidx = np.where(is_b, 0, -1 - index)
        pv, ps = np.r_[pts_vertex, -1], np.r_[pts_source, 0].astype(np.int8)  # pidx 0 is valid when pts is empty
        vtab = np.where(is_b, ch.vertex[np.where(is_b, index, 0)], pv[pidx])
        vid = np.where(vtab >= 0, vertex_ids[np.maximum(vtab, 0)], local_ids(pidx, "rebuilt"))  # new vertices
        xs.append(xyz)
        ids.append(vid)
        fs.append(tri + base)
        srcs.append(np.where(is_b, 0, ps[pidx]).astype(np.int8))
        chs.append(np.full(len(tri), ci, np.int32))
        base += len(xyz)
    if not xs:
        return empty_mesh()
    xyz, vid, faces = np.concatenate(xs), np.concatenate(ids), np.concatenate(fs)
    src, chart = np.concatenate(srcs), np.concatenate(chs)
    # weld: one vertex per id (charts touching at a vertex, a point used by two charts)
    uid, first, inv = np.unique(vid, return_index=True, return_inverse=True)
    faces = inv.reshape(-1)[faces]
    good = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return RebuiltMesh(xyz[first], uid, faces[good], src[first], chart[good], stats)


def _locate_in_charts(charts: list[Chart], pts: np.ndarray) -> tuple[np.ndarray, list[tuple]]:
    """Each point's nearest chart and its foot there, from one closest-point query over every chart's
    faces (not one query of all points per chart). Returns ((k,) int64 owner chart, per chart the
    ``ClosestPoint.query`` triple of all points, meaningful where that chart owns the point)."""
    if not charts or not len(pts):
        return np.zeros(len(pts), np.int64), [ClosestPoint(ch.xyz, ch.faces).query(pts) for ch in charts]
    v_base = np.cumsum([0] + [len(ch.xyz) for ch in charts[:-1]])
    f_base = np.cumsum([0] + [len(ch.faces) for ch in charts])
    xyz = np.concatenate([ch.xyz for ch in charts])
    faces = np.concatenate([ch.faces + b for ch, b in zip(charts, v_base)])
    fid, bary, dist = ClosestPoint(xyz, faces).query(pts)
    owner = np.clip(np.searchsorted(f_base, fid, side="right") - 1, 0, len(charts) - 1)
    local = np.where((fid >= 0) & (fid < len(faces)), fid - f_base[owner], -1)
    return owner, [(local, bary, dist)] * len(charts)


# ------------------------------------------------------------------------------------- stitching checks

def border_edges(zone_faces: np.ndarray, context_faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Undirected edges (vertex-table indices) shared by a zone face and a retained (context) face: (b, 2)."""
    ez, ec = edges_of(zone_faces), edges_of(context_faces)
    kz, kc = undirected_key(ez, n_vertices), undirected_key(ec, n_vertices)
    both = np.intersect1d(kz, kc)
    return np.c_[both // n_vertices, both % n_vertices]


def border_gap(border_xyz: np.ndarray, border_ids: np.ndarray, rebuilt: RebuiltMesh, step_m: float = 0.01) -> dict:
    """How well the rebuilt mesh closes onto the retained border.

    border_xyz: (b, 2, 3) end points of the retained border edges; border_ids: (b, 2) their vertex ids.
    Returns {"border_edges", "welded" (edges present in the rebuilt mesh with the same two ids),
    "max_gap_m" (largest distance from a point of a border edge to the rebuilt surface: 0 when all are
    welded), "open_edges" (rebuilt boundary edges that are not border edges: holes left inside)}.
    """
    out = {"border_edges": len(border_ids), "welded": 0, "max_gap_m": 0.0, "open_edges": 0}
    if rebuilt.n_faces == 0:
        out["max_gap_m"] = float("inf") if len(border_ids) else 0.0
        return out
    border_ids = np.asarray(border_ids, np.int64).reshape(-1, 2)
    welded = _id_edges_in(border_ids, rebuilt.vertex_id[edges_of(rebuilt.faces)])
    out["welded"] = int(welded.sum())
    if (~welded).any():
        bx = np.asarray(border_xyz, np.float64)[~welded]
        flat = bx.reshape(-1, 3)
        pts = _segment_samples(flat, np.arange(len(flat)).reshape(-1, 2), step_m)
        _, _, d = ClosestPoint(rebuilt.xyz, rebuilt.faces).query(pts)
        out["max_gap_m"] = float(d.max()) if len(d) else 0.0
    bid = rebuilt.vertex_id[boundary_edges(rebuilt.faces, len(rebuilt.xyz))]
    out["open_edges"] = int((~_id_edges_in(bid, border_ids)).sum())
    return out


def _id_edges_in(query: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(q,) bool: each undirected edge of ``query`` (q, 2) int64 vertex ids is among those of ``ref`` (r, 2).

    >>> _id_edges_in(np.array([[5, -9], [5, 7]]), np.array([[-9, 5], [1 << 60, 3]])).tolist()
    [True, False]
    """
    q, r = np.asarray(query, np.int64).reshape(-1, 2), np.asarray(ref, np.int64).reshape(-1, 2)
    u, inv = np.unique(np.concatenate([q.ravel(), r.ravel()]), return_inverse=True)
    inv = inv.reshape(-1, 2)
    key = np.minimum(inv[:, 0], inv[:, 1]) * max(len(u), 1) + np.maximum(inv[:, 0], inv[:, 1])
    return np.isin(key[:len(q)], key[len(q):])
