"""Compiled (numba) loops for the per-point geometry the numpy versions paid for in temporaries.

Each kernel replaces a vectorised numpy expression that built (n, k, 3) neighbour arrays or (n, 3, 3)
matrices and then called LAPACK once per 3x3 matrix; here one pass per point does the same arithmetic in
registers. ``benchmarks/kernel_bench.py`` times each against the numpy code it replaced, k-d tree queries
included (both share them): PCA normals of 500 k points 1.5x faster, the plane + edge test 2.1x, the 5 cm
voxel thinning 1.5x, closest points on triangles 5x, the cues' point -> mesh distance from 8 candidates 13x
(after the query).

Closest points on triangles keep their vectorised numpy form beside the kernel
(:func:`closest_points_numpy`): the point-to-mesh distance of :mod:`tasks.geometry.distance` re-measures
with it, and its figures were made with it.

All kernels are ``cache=True``: the first call on a machine compiles them (~1-3 s each) into
``__pycache__``, later processes load them.

The symmetric 3x3 eigen-solver is cyclic Jacobi (Golub & Van Loan §8.5): accurate to machine precision
for the tiny smallest eigenvalue of a plane's covariance, where a closed-form cubic loses digits.
Eigenvectors are defined up to sign, as LAPACK's are.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["closest_point_on_triangles", "closest_points_numpy", "closest_points_on_triangles", "eig3", "knn_pca",
           "local_planes", "nearest_of_candidates", "nearest_to_centroid"]


@njit(cache=True, nogil=True)
def eig3(a: np.ndarray, w: np.ndarray, v: np.ndarray) -> None:
    """Eigen-decomposition of the symmetric (3, 3) float64 matrix ``a`` (overwritten): ascending eigenvalues
    into ``w`` (3,), unit eigenvectors into the columns of ``v`` (3, 3)."""
    for i in range(3):
        for j in range(3):
            v[i, j] = 1.0 if i == j else 0.0
    for _ in range(32):
        off = a[0, 1] * a[0, 1] + a[0, 2] * a[0, 2] + a[1, 2] * a[1, 2]
        diag = a[0, 0] * a[0, 0] + a[1, 1] * a[1, 1] + a[2, 2] * a[2, 2]
        if off == 0.0 or off <= 1e-36 * diag:
            break
        for p, q in ((0, 1), (0, 2), (1, 2)):
            apq = a[p, q]
            if apq == 0.0:
                continue
            theta = (a[q, q] - a[p, p]) / (2.0 * apq)
            if abs(theta) > 1e150:
                t = 0.5 / theta
            else:
                t = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
            c = 1.0 / math.sqrt(t * t + 1.0)
            s = t * c
            for k in range(3):  # a <- a J, then J^T a, v <- v J
                akp, akq = a[k, p], a[k, q]
                a[k, p], a[k, q] = c * akp - s * akq, s * akp + c * akq
            for k in range(3):
                apk, aqk = a[p, k], a[q, k]
                a[p, k], a[q, k] = c * apk - s * aqk, s * apk + c * aqk
            for k in range(3):
                vkp, vkq = v[k, p], v[k, q]
                v[k, p], v[k, q] = c * vkp - s * vkq, s * vkp + c * vkq
    d0, d1, d2 = a[0, 0], a[1, 1], a[2, 2]
    i0, i1, i2 = 0, 1, 2  # sort the three (value, column) pairs ascending
    if d0 > d1:
        d0, d1, i0, i1 = d1, d0, i1, i0
    if d1 > d2:
        d1, d2, i1, i2 = d2, d1, i2, i1
    if d0 > d1:
        d0, d1, i0, i1 = d1, d0, i1, i0
    w[0], w[1], w[2] = d0, d1, d2
    for k in range(3):
        c0, c1, c2 = v[k, i0], v[k, i1], v[k, i2]
        v[k, 0], v[k, 1], v[k, 2] = c0, c1, c2


@njit(cache=True, nogil=True)
def _fit(buf: np.ndarray, cnt: int, a: np.ndarray, w: np.ndarray, v: np.ndarray) -> None:
    """Eigen-decomposition (:func:`eig3` into w, v) of the covariance (divided by cnt) of the points
    buf[:cnt] (buf: (k, 3) float64, cnt >= 1); a: (3, 3) scratch."""
    mx = my = mz = 0.0
    for t in range(cnt):
        mx += buf[t, 0]
        my += buf[t, 1]
        mz += buf[t, 2]
    mx, my, mz = mx / cnt, my / cnt, mz / cnt
    sxx = sxy = sxz = syy = syz = szz = 0.0
    for t in range(cnt):
        dx, dy, dz = buf[t, 0] - mx, buf[t, 1] - my, buf[t, 2] - mz
        sxx += dx * dx
        sxy += dx * dy
        sxz += dx * dz
        syy += dy * dy
        syz += dy * dz
        szz += dz * dz
    a[0, 0], a[0, 1], a[0, 2] = sxx / cnt, sxy / cnt, sxz / cnt
    a[1, 0], a[1, 1], a[1, 2] = sxy / cnt, syy / cnt, syz / cnt
    a[2, 0], a[2, 1], a[2, 2] = sxz / cnt, syz / cnt, szz / cnt
    eig3(a, w, v)


@njit(cache=True, nogil=True)
def knn_pca(xyz: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """PCA of each point's neighbourhood: xyz (n, 3) float64, idx (n, k) int64 rows of xyz (the point's k
    nearest, itself included). Returns ((n, 3) float64 least-variance unit direction, (n,) float64 surface
    variation λ0 / max(λ0 + λ1 + λ2, 1e-18)); the covariance is divided by k."""
    n, k = idx.shape
    normals = np.empty((n, 3))
    variation = np.empty(n)
    a, w, v, buf = np.empty((3, 3)), np.empty(3), np.empty((3, 3)), np.empty((k, 3))
    for i in range(n):
        for j in range(k):
            buf[j, 0], buf[j, 1], buf[j, 2] = xyz[idx[i, j], 0], xyz[idx[i, j], 1], xyz[idx[i, j], 2]
        _fit(buf, k, a, w, v)
        normals[i, 0], normals[i, 1], normals[i, 2] = v[0, 0], v[1, 0], v[2, 0]
        variation[i] = w[0] / max(w[0] + w[1] + w[2], 1e-18)
    return normals, variation


@njit(cache=True, nogil=True)
def local_planes(q: np.ndarray, ref: np.ndarray, j: np.ndarray, d: np.ndarray, tolerance_m: float,
                 edges: bool, max_gap: float) -> np.ndarray:
    """(n,) bool: the plane test of :func:`tasks.repair.coarsen.flat_points` for n query points.

    q: (n, 3) query points, ref: (m, 3) reference points (same local frame, float32 or float64); j, d:
    (n, k) the k-d tree's neighbour rows of ref and distances, inf where none within the radius. A point
    passes when it has >= 6 neighbours, their RMS distance to their best-fit plane is <= ``tolerance_m``
    and (``edges``) no empty angular sector of them around it in that plane is wider than ``max_gap``
    radians (neighbours at distance <= 1e-9 m do not count for the sector)."""
    n, k = j.shape
    out = np.zeros(n, np.bool_)
    a, w, v = np.empty((3, 3)), np.empty(3), np.empty((3, 3))
    rel = np.empty((k, 3))
    ang = np.empty(k)
    for i in range(n):
        cnt = 0
        for t in range(k):
            if math.isfinite(d[i, t]):
                r = j[i, t]
                rel[cnt, 0] = ref[r, 0] - q[i, 0]
                rel[cnt, 1] = ref[r, 1] - q[i, 1]
                rel[cnt, 2] = ref[r, 2] - q[i, 2]
                ang[cnt] = d[i, t]  # the distance, kept beside its offset for the sector test
                cnt += 1
        if cnt < 6:
            continue
        _fit(rel, cnt, a, w, v)
        if math.sqrt(max(w[0], 0.0)) > tolerance_m:
            continue
        if edges:
            m = 0
            for t in range(cnt):
                if ang[t] > 1e-9:
                    x = rel[t, 0] * v[0, 2] + rel[t, 1] * v[1, 2] + rel[t, 2] * v[2, 2]
                    y = rel[t, 0] * v[0, 1] + rel[t, 1] * v[1, 1] + rel[t, 2] * v[2, 1]
                    ang[m] = math.atan2(y, x)
                    m += 1
            if m < 2:
                continue
            s = np.sort(ang[:m])
            gap = s[0] + 2.0 * math.pi - s[m - 1]
            for t in range(m - 1):
                gap = max(gap, s[t + 1] - s[t])
            if gap > max_gap:
                continue
        out[i] = True
    return out


@njit(cache=True, nogil=True)
def nearest_to_centroid(xyz: np.ndarray, order: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """For groups of rows of xyz (n, 3) float64 given as ``order`` (n,) int64 sorted by group, rows
    ascending within a group, and ``starts`` (g,) int64 the first position of each group in ``order``: the
    row of each group nearest its centroid, the first such row on a tie. Returns (g,) int64."""
    g = len(starts)
    n = len(order)
    out = np.empty(g, np.int64)
    for s in range(g):
        lo = starts[s]
        hi = starts[s + 1] if s + 1 < g else n
        mx = my = mz = 0.0
        for t in range(lo, hi):
            r = order[t]
            mx += xyz[r, 0]
            my += xyz[r, 1]
            mz += xyz[r, 2]
        c = hi - lo
        mx, my, mz = mx / c, my / c, mz / c
        best, pick = np.inf, order[lo]
        for t in range(lo, hi):
            r = order[t]
            dx, dy, dz = xyz[r, 0] - mx, xyz[r, 1] - my, xyz[r, 2] - mz
            dd = math.sqrt(dx * dx + dy * dy + dz * dz)
            if dd < best:
                best, pick = dd, r
        out[s] = pick
    return out


@njit(cache=True, nogil=True)
def _closest_on_segment(px, py, pz, ax, ay, az, bx, by, bz):
    ux, uy, uz = bx - ax, by - ay, bz - az
    l2 = ux * ux + uy * uy + uz * uz
    t = 0.0
    if l2 > 0:
        t = min(max(((px - ax) * ux + (py - ay) * uy + (pz - az) * uz) / l2, 0.0), 1.0)
    return ax + ux * t, ay + uy * t, az + uz * t


@njit(cache=True, nogil=True)
def _closest(px: float, py: float, pz: float, tri: np.ndarray, f: int) -> tuple[float, float, float]:
    """Closest point of (px, py, pz) on triangle tri[f] (Ericson §5.1.5; degenerate: its longest side)."""
    ax, ay, az = tri[f, 0, 0], tri[f, 0, 1], tri[f, 0, 2]
    bx, by, bz = tri[f, 1, 0], tri[f, 1, 1], tri[f, 1, 2]
    cx, cy, cz = tri[f, 2, 0], tri[f, 2, 1], tri[f, 2, 2]
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    nx, ny, nz = aby * acz - abz * acy, abz * acx - abx * acz, abx * acy - aby * acx
    if nx == 0.0 and ny == 0.0 and nz == 0.0:  # degenerate: the longest of the three sides
        l0 = abx * abx + aby * aby + abz * abz
        l1 = (cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2
        l2 = acx * acx + acy * acy + acz * acz
        if l0 >= l1 and l0 >= l2:
            return _closest_on_segment(px, py, pz, ax, ay, az, bx, by, bz)
        if l1 >= l2:
            return _closest_on_segment(px, py, pz, bx, by, bz, cx, cy, cz)
        return _closest_on_segment(px, py, pz, cx, cy, cz, ax, ay, az)
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0 and d2 <= 0:
        return ax, ay, az
    bpx, bpy, bpz = px - bx, py - by, pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0 and d4 <= d3:
        return bx, by, bz
    vc = d1 * d4 - d3 * d2
    if vc <= 0 and d1 >= 0 and d3 <= 0:
        v = d1 / (d1 - d3)
        return ax + abx * v, ay + aby * v, az + abz * v
    cpx, cpy, cpz = px - cx, py - cy, pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0 and d5 <= d6:
        return cx, cy, cz
    vb = d5 * d2 - d1 * d6
    if vb <= 0 and d2 >= 0 and d6 <= 0:
        w = d2 / (d2 - d6)
        return ax + acx * w, ay + acy * w, az + acz * w
    va = d3 * d6 - d5 * d4
    if va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return bx + (cx - bx) * w, by + (cy - by) * w, bz + (cz - bz) * w
    denom = va + vb + vc
    v, w = vb / denom, vc / denom
    return ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w


@njit(cache=True, nogil=True)
def closest_points_on_triangles(p: np.ndarray, tri: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Closest point of p[i] (p: (q, 3) float64) on triangle tri[rows[i]] (tri: (m, 3, 3) float64; rows:
    (q,) int64), Ericson's Real-Time Collision Detection §5.1.5 region by region. A zero-area triangle
    (its edge cross product exactly 0) gives the closest point on its longest side. Returns (q, 3)."""
    out = np.empty((len(rows), 3))
    for i in range(len(rows)):
        out[i, 0], out[i, 1], out[i, 2] = _closest(p[i, 0], p[i, 1], p[i, 2], tri, rows[i])
    return out


def closest_point_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Closest points on triangles, row by row (:func:`closest_points_on_triangles` with ``rows = arange``).

    p: (q, 3) float64 points; tri: (q, 3, 3) float64 triangles. Returns (q, 3) float64. A degenerate
    triangle (zero area: a segment or a point) gives the closest point on its longest side.

    >>> t = np.array([[[0., 0, 0], [1, 0, 0], [0, 1, 0]]] * 3)
    >>> closest_point_on_triangles(np.array([[.2, .2, 1], [2, 2, 0], [-1, -1, 0]]), t).round(6).tolist()
    [[0.2, 0.2, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 0.0]]
    >>> closest_point_on_triangles(np.array([[.5, 1, 0]]), np.array([[[0., 0, 0], [0, 0, 0], [2, 0, 0]]])).tolist()
    [[0.5, 0.0, 0.0]]
    """
    tri = np.ascontiguousarray(tri, np.float64).reshape(-1, 3, 3)
    return closest_points_on_triangles(np.ascontiguousarray(p, np.float64).reshape(-1, 3), tri,
                                       np.arange(len(tri), dtype=np.int64))


def closest_points_numpy(p, a, b, c) -> np.ndarray:
    """The same regions vectorised with ``np.where`` (the code the kernel replaced): closest point of each
    triangle (a, b, c) to p, all (n, 3) float64 -> (n, 3) float64.

    Not bit-identical to the kernel (every foot is reached as ``a + v ab + w ac``: about one in nine
    differs in its last bits), and a zero-area triangle may give NaN (its interior ratio is 0 / 0) where the
    kernel takes the longest side. :class:`tasks.geometry.distance.MeshDistance` re-measures with this form
    and keeps open3d's float32 distance where it is NaN.

    >>> t = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> closest_points_numpy(np.array([[.2, .2, 1.]]), *(t[[k]] for k in range(3))).round(6).tolist()
    [[0.2, 0.2, 0.0]]
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


@njit(cache=True, nogil=True)
def nearest_of_candidates(p: np.ndarray, tri: np.ndarray, normals: np.ndarray, radius: np.ndarray,
                          cand: np.ndarray, cand_d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unsigned and signed distance (q,) float64 of each point p[i] (p: (q, 3)) to the nearest of its
    candidate faces cand[i] (cand: (q, k) int64 rows of tri (m, 3, 3), m where there is none; cand_d:
    (q, k) their centres' distances, the nearest first; normals: (m, 3) unit; radius: (m,) each face's
    largest corner distance from its centre).

    The exact distance is computed for the first candidate, then only for a candidate whose lower bounds
    (centre distance minus radius, and distance to its plane) are within it (1e-9 relative slack): the others
    cannot be nearer. The first of equal distances wins. The sign is that of the offset from the foot along
    the chosen face's normal (0 on the face). Third output: that offset itself (q,) float64, the component of
    the point's offset from its foot along the face normal (its square subtracted from the distance's square
    leaves the in-plane part: a point beyond a face's edge in the face's plane has offset ~0)."""
    q, k = cand.shape
    m = len(tri)
    d_out, s_out, o_out = np.empty(q), np.empty(q), np.empty(q)
    for i in range(q):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        fb = cand[i, 0]
        nx, ny, nz = _closest(px, py, pz, tri, fb)
        best = math.sqrt((nx - px) ** 2 + (ny - py) ** 2 + (nz - pz) ** 2)
        bound = best + 1e-9 * (1.0 + best)
        for c in range(1, k):
            f = cand[i, c]
            if f >= m or cand_d[i, c] - radius[f] > bound:
                continue
            if abs((px - tri[f, 0, 0]) * normals[f, 0] + (py - tri[f, 0, 1]) * normals[f, 1]
                   + (pz - tri[f, 0, 2]) * normals[f, 2]) > bound:
                continue
            qx, qy, qz = _closest(px, py, pz, tri, f)
            dd = math.sqrt((qx - px) ** 2 + (qy - py) ** 2 + (qz - pz) ** 2)
            if dd < best:
                best, fb, nx, ny, nz = dd, f, qx, qy, qz
        off = (px - nx) * normals[fb, 0] + (py - ny) * normals[fb, 1] + (pz - nz) * normals[fb, 2]
        d_out[i] = best
        s_out[i] = (1.0 if off > 0 else (-1.0 if off < 0 else 0.0)) * best
        o_out[i] = off
    return d_out, s_out, o_out
