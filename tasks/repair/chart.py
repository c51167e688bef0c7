"""The chart of a region: the faces it replaces, made into discs and mapped onto the unit disc.

A region's rebuilt mesh must weld exactly to the retained mesh. We get that by construction: the
faces being replaced (the *zone*), with their holes filled, form a surface whose boundary is the
retained border; each connected piece that is a topological disc is mapped onto the unit disc
(Floater's mean-value parameterisation, boundary on the circle by arc length). Fused points are
located on the zone surface and carried into the disc; a 2D Delaunay triangulation of them together
with the boundary vertices then has the boundary polygon as its convex hull, so every border edge
of the retained mesh is an edge of the rebuilt mesh (same two vertex ids): no gap, no overlap.

Functions here are pure: arrays of vertex ids, positions and faces in, arrays out.
Frames and units: campus-local metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components
from scipy.sparse.linalg import spsolve

from tasks.repair.conformal import conformal_uv


def edges_of(faces: np.ndarray) -> np.ndarray:
    """(m, 3) int faces -> (3m, 2) directed edges (v0 v1, v1 v2, v2 v0), face-major."""
    f = np.asarray(faces, np.int64)
    return np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)


def undirected_key(e: np.ndarray, n: int) -> np.ndarray:
    return np.minimum(e[:, 0], e[:, 1]) * n + np.maximum(e[:, 0], e[:, 1])


def boundary_edges(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Directed edges used by exactly one face (in that face's orientation): (b, 2) int64."""
    e = edges_of(faces)
    key = undirected_key(e, n_vertices)
    _, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
    return e[cnt[inv.reshape(-1)] == 1]


def trace_loops(directed: np.ndarray) -> tuple[list[np.ndarray], bool]:
    """Chain directed boundary edges into closed loops of vertex indices.

    Returns (loops, clean); clean is False when a vertex starts more than one boundary edge (a
    pinched boundary) or an edge chain does not close, in which case the loops are unreliable.
    """
    if len(directed) == 0:
        return [], True
    start = {}
    clean = True
    for a, b in directed.tolist():
        if a in start:
            clean = False
        start[a] = b
    loops, seen = [], set()
    for a0 in list(start):
        if a0 in seen:
            continue
        loop, a = [], a0
        while a not in seen:
            seen.add(a)
            loop.append(a)
            a = start.get(a)
            if a is None:
                clean = False
                break
        if a != a0:
            clean = False
        loops.append(np.asarray(loop, np.int64))
    return loops, clean


def loop_length(xyz: np.ndarray, loop: np.ndarray) -> float:
    p = xyz[loop]
    return float(np.linalg.norm(p - np.roll(p, -1, axis=0), axis=1).sum())


def fill_loop(xyz: np.ndarray, loop: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Close a hole: a fan from a new vertex at the loop's centroid.

    loop: (k,) vertex indices in the orientation of the boundary edges of the surrounding faces
    (the hole is on their right); the fan runs the other way, so it is oriented like them.
    Returns ((1, 3) the new vertex, (k, 3) faces with the new vertex as index ``len(xyz)``).
    """
    c = len(xyz)
    nxt = np.roll(loop, -1)
    return xyz[loop].mean(axis=0, keepdims=True), np.stack([nxt, loop, np.full(len(loop), c)], axis=1)


def face_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Label of each face: components connected through shared edges. (m, 3) -> (m,) int64."""
    m = len(faces)
    if m == 0:
        return np.zeros(0, np.int64)
    e = edges_of(faces)
    key = undirected_key(e, n_vertices)
    fid = np.repeat(np.arange(m), 3)
    order = np.argsort(key, kind="stable")
    k, f = key[order], fid[order]
    same = k[1:] == k[:-1]
    a, b = f[:-1][same], f[1:][same]
    g = coo_matrix((np.ones(len(a)), (a, b)), shape=(m, m))
    return connected_components(g, directed=False)[1].astype(np.int64)


def split_fans(faces: np.ndarray, n_vertices: int, cut_keys: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Give each fan of faces around a vertex its own copy of the vertex.

    Two corners of a vertex share a copy when their faces share an edge at that vertex that is used by
    exactly two faces and is not in ``cut_keys`` (undirected keys, :func:`undirected_key`). This
    separates pinched boundaries (a vertex where the boundary touches itself), non-manifold edges and,
    with cut edges, the two sides of a seam. faces: (m, 3). Returns ((m, 3) faces into the copies,
    (c,) int64 original vertex of each copy).
    """
    f = np.asarray(faces, np.int64)
    m = len(f)
    if m == 0:
        return f.reshape(0, 3), np.zeros(0, np.int64)
    e = edges_of(f)  # edge k of face i: (f[i,k], f[i,k+1]), corners 3i+k and 3i+(k+1)%3
    key = undirected_key(e, n_vertices)
    corner_a = np.arange(3 * m)
    corner_b = (corner_a // 3) * 3 + (corner_a % 3 + 1) % 3
    order = np.argsort(key, kind="stable")
    k = key[order]
    _, start, cnt = np.unique(k, return_index=True, return_counts=True)
    two = start[cnt == 2]
    i1, i2 = order[two], order[two + 1]
    ok = np.ones(len(i1), bool)
    if cut_keys is not None and len(cut_keys):
        ok &= ~np.isin(key[i1], cut_keys)
    i1, i2 = i1[ok], i2[ok]
    # the shared edge runs a->b in one face and b->a in the other (or a->b in both when misoriented)
    same_dir = e[i1, 0] == e[i2, 0]
    a1, b1 = corner_a[i1], corner_b[i1]
    a2 = np.where(same_dir, corner_a[i2], corner_b[i2])
    b2 = np.where(same_dir, corner_b[i2], corner_a[i2])
    rows = np.r_[a1, b1]
    cols = np.r_[a2, b2]
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * m, 3 * m))
    _, comp = connected_components(g, directed=False)
    copies, new_index = np.unique(comp, return_inverse=True)
    orig = np.zeros(len(copies), np.int64)
    orig[new_index] = f.ravel()
    return new_index.reshape(m, 3).astype(np.int64), orig


def seam_edges(xyz: np.ndarray, faces: np.ndarray, loops: list[np.ndarray]) -> np.ndarray:
    """Undirected keys of the edges of shortest paths that join every other loop to the longest one.

    After cutting along them (:func:`split_fans`) a connected surface with several boundary loops
    has one. Paths run through interior vertices (Dijkstra over edge lengths), each inner loop joined
    to the outer loop or to a loop already joined.
    """
    from scipy.sparse.csgraph import dijkstra

    n = len(xyz)
    e = edges_of(faces)
    key = np.unique(undirected_key(e, n))
    a, b = key // n, key % n
    w = np.linalg.norm(xyz[a] - xyz[b], axis=1) + 1e-9
    on_loop = np.full(n, -1)
    for li, lp in enumerate(loops):
        on_loop[lp] = li
    lengths = [loop_length(xyz, lp) for lp in loops]
    outer = int(np.argmax(lengths))
    joined = {outer}
    cut = []
    # an edge between two boundary vertices of different loops, or along a loop, is not a path edge
    # except as a direct bridge; weights stay, the path search starts from the joined set
    g = coo_matrix((np.r_[w, w], (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    while len(joined) < len(loops):
        src = np.concatenate([loops[i] for i in sorted(joined)])
        dist, pred, _source = dijkstra(g, indices=src, return_predecessors=True, min_only=True)
        best, target = np.inf, None
        for li in set(range(len(loops))) - joined:
            v = loops[li][np.argmin(dist[loops[li]])]
            if dist[v] < best:
                best, target = dist[v], (li, v)
        if target is None:  # not connected (should not happen within one component)
            break
        li, v = target
        path = [v]
        while pred[path[-1]] >= 0:
            path.append(pred[path[-1]])
        p = np.asarray(path)
        cut.append(undirected_key(np.c_[p[:-1], p[1:]], n))
        joined.add(li)
    return np.concatenate(cut) if cut else np.zeros(0, np.int64)


def opening_cut(xyz: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Undirected keys of a shortest edge path between two far-apart vertices of a closed surface: cut
    along it (:func:`split_fans`), a sphere-like surface becomes a disc whose boundary is the path twice."""
    from scipy.sparse.csgraph import dijkstra

    n = len(xyz)
    key = np.unique(undirected_key(edges_of(faces), n))
    a, b = key // n, key % n
    w = np.linalg.norm(xyz[a] - xyz[b], axis=1) + 1e-9
    g = coo_matrix((np.r_[w, w], (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    d0 = dijkstra(g, indices=int(faces[0, 0]))
    far = int(np.argmax(np.where(np.isfinite(d0), d0, -1)))
    dist, pred = dijkstra(g, indices=far, return_predecessors=True)
    end = int(np.argmax(np.where(np.isfinite(dist), dist, -1)))
    path = [end]
    while pred[path[-1]] >= 0:
        path.append(int(pred[path[-1]]))
    p = np.asarray(path)
    return undirected_key(np.c_[p[:-1], p[1:]], n)


def mean_value_weights(xyz: np.ndarray, faces: np.ndarray) -> csr_matrix:
    """Floater's mean-value weights w_ij = (tan(a/2) + tan(b/2)) / |x_i - x_j| (always positive)."""
    n = len(xyz)
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, l = faces[:, k], faces[:, (k + 1) % 3], faces[:, (k + 2) % 3]
        eij, eil = xyz[j] - xyz[i], xyz[l] - xyz[i]
        nij, nil = np.linalg.norm(eij, axis=1), np.linalg.norm(eil, axis=1)
        cosang = np.einsum("ij,ij->i", eij, eil) / np.maximum(nij * nil, 1e-18)
        half = 0.5 * np.arccos(np.clip(cosang, -1.0, 1.0))
        t = np.tan(half)
        # the angle at i lies between edges ij and il: it contributes to w_ij and w_il
        rows += [i, i]
        cols += [j, l]
        vals += [t / np.maximum(nij, 1e-12), t / np.maximum(nil, 1e-12)]
    w = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n))
    return w.tocsr()


def disc_parameterisation(xyz: np.ndarray, faces: np.ndarray, loop: np.ndarray) -> np.ndarray:
    """Map a disc-like triangle mesh onto the unit disc.

    xyz: (n, 3) float64; faces: (m, 3) int (every vertex used); loop: (k,) its boundary loop in
    face orientation. Boundary vertices go to the circle by arc length, counter-clockwise, so faces
    map to counter-clockwise triangles; interior vertices solve the mean-value Laplace system
    (a valid embedding for any weights > 0, Floater 2003). Returns (n, 2) float64.
    """
    n = len(xyz)
    p = xyz[loop]
    seg = np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1)
    s = np.r_[0.0, np.cumsum(seg)[:-1]] / max(seg.sum(), 1e-18)
    # the hole of the surrounding surface is on the right of a boundary edge, the disc on its left:
    # walking the loop keeps the disc on the left, i.e. counter-clockwise around it
    ang = 2 * np.pi * s
    uv = np.zeros((n, 2))
    uv[loop] = np.c_[np.cos(ang), np.sin(ang)]
    is_b = np.zeros(n, bool)
    is_b[loop] = True
    inner = np.flatnonzero(~is_b)
    if len(inner):
        w = mean_value_weights(xyz, faces)
        w = w.tocsr()
        deg = np.asarray(w.sum(axis=1)).ravel()
        a = (csr_matrix((deg, (np.arange(n), np.arange(n))), shape=(n, n)) - w).tocsr()
        a_ii = a[inner][:, inner]
        rhs = -(a[inner][:, np.flatnonzero(is_b)] @ uv[is_b])
        sol = spsolve(a_ii.tocsc(), rhs)
        uv[inner] = np.asarray(sol).reshape(len(inner), 2)
    return uv


@dataclass(frozen=True)
class Chart:
    """One disc of a region's zone, mapped onto the unit disc.

    xyz: (n, 3) float64 chart vertices (zone vertices + hole-fill centres); vertex: (n,) int64 index
    into the region's vertex table, -1 for a fill centre; faces: (m, 3) int64 into xyz; uv: (n, 2)
    float64 disc coordinates; loop: (k,) boundary loop (indices into xyz), counter-clockwise in uv;
    zone_face: (m,) int64 index of the zone face (-1 for a fill face). A vertex may appear more than
    once (copies at a pinch or on the two sides of a seam); copies share their ``vertex``.
    cuv: (n, 2) float64 conformal coordinates (metres, :func:`tasks.repair.conformal.conformal_uv`), or
    None where that map folds: then the chart is triangulated in the disc.
    """

    xyz: np.ndarray
    vertex: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    loop: np.ndarray
    zone_face: np.ndarray
    cuv: np.ndarray | None = None


@dataclass(frozen=True)
class ZoneTopology:
    """charts: the disc pieces; rejected: zone face indices of pieces that are not discs (left to the
    mesh); holes_filled: number of hole loops closed; hole_length_m: their total rim length."""

    charts: list[Chart]
    rejected: np.ndarray
    holes_filled: int
    hole_length_m: float
    seams: int = 0


def zone_charts(xyz: np.ndarray, zone_faces: np.ndarray, context_faces: np.ndarray, near_zone: np.ndarray,
                max_hole_loop_m: float, conformal: bool = True) -> ZoneTopology:
    """Split a region's zone into disc charts.

    xyz: (n, 3) float64 region vertex table (zone and context vertices); zone_faces (mz, 3) and
    context_faces (mc, 3) int64 into it; near_zone: (n,) bool vertices close enough to the zone that
    a mesh boundary through them is a hole of the zone rather than the edge of what was read.
    Boundary loops of zone + context shorter than ``max_hole_loop_m`` whose vertices are all near the
    zone and that touch a zone face are holes: filled (fan) and added to the zone. Each face
    component of the result with one clean boundary loop becomes a :class:`Chart` (with its conformal
    map too when ``conformal``).
    """
    n = len(xyz)
    zone_faces = np.asarray(zone_faces, np.int64).reshape(-1, 3)
    context_faces = np.asarray(context_faces, np.int64).reshape(-1, 3)
    allf = np.concatenate([zone_faces, context_faces])
    in_zone_v = np.zeros(n, bool)
    in_zone_v[zone_faces.ravel()] = True
    loops, _ = trace_loops(boundary_edges(allf, n))
    verts, faces, src = [xyz], [zone_faces], [np.arange(len(zone_faces))]
    n_fill, fill_len = 0, 0.0
    nxt = n
    for lp in loops:
        if len(lp) < 3 or not near_zone[lp].all() or not in_zone_v[lp].any():
            continue
        length = loop_length(xyz, lp)
        if length > max_hole_loop_m:
            continue
        c, f = fill_loop(xyz, lp)
        f[:, 2] = nxt
        nxt += 1
        verts.append(c)
        faces.append(f)
        src.append(np.full(len(f), -1))
        n_fill += 1
        fill_len += length
    vx = np.concatenate(verts)
    fz = np.concatenate(faces)
    zf = np.concatenate(src)
    fz_split, orig = split_fans(fz, len(vx))
    lab = face_components(fz_split, len(orig))
    charts, rejected = [], []
    n_seams = 0
    for c in range(int(lab.max()) + 1 if len(lab) else 0):
        sel = lab == c
        used, inv = np.unique(fz_split[sel], return_inverse=True)
        fl = inv.reshape(-1, 3)
        vo = orig[used]
        lps, clean = trace_loops(boundary_edges(fl, len(used)))
        if clean and len(lps) == 0 and len(fl) >= 4:  # a closed surface: cut it open along a path
            cut = opening_cut(vx[vo], fl)
            fl2, o2 = split_fans(fl, len(used), cut)
            lps2, clean2 = trace_loops(boundary_edges(fl2, len(o2)))
            if clean2 and len(lps2) == 1:
                fl, vo, lps, clean = fl2, vo[o2], lps2, clean2
                n_seams += 1
        if clean and len(lps) > 1:
            cut = seam_edges(vx[vo], fl, lps)
            fl2, o2 = split_fans(fl, len(used), cut)
            lps2, clean = trace_loops(boundary_edges(fl2, len(o2)))
            if clean and len(lps2) == 1:
                fl, vo, lps = fl2, vo[o2], lps2
                n_seams += len(lps) and 1
        if not clean or len(lps) != 1 or len(lps[0]) < 3 or not _manifold(fl, len(vo)):
            rejected.append(zf[sel][zf[sel] >= 0])
            continue
        uv = disc_parameterisation(vx[vo], fl, lps[0])
        cuv = conformal_uv(vx[vo], fl, lps[0]) if conformal else None
        charts.append(Chart(xyz=vx[vo], vertex=np.where(vo < n, vo, -1), faces=fl, uv=uv, loop=lps[0],
                            zone_face=zf[sel], cuv=cuv))
    rej = np.concatenate(rejected) if rejected else np.zeros(0, np.int64)
    return ZoneTopology(charts, rej, n_fill, fill_len, n_seams)


def _manifold(faces: np.ndarray, n: int) -> bool:
    """Every edge used by at most two faces, with opposite orientations (consistently oriented)."""
    e = edges_of(faces)
    key = e[:, 0] * n + e[:, 1]
    if len(np.unique(key)) != len(key):  # a directed edge used twice: flipped face or non-manifold
        return False
    _, cnt = np.unique(undirected_key(e, n), return_counts=True)
    return bool((cnt <= 2).all())
