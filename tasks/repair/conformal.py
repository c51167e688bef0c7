"""A near-isometric chart map and a constrained Delaunay triangulation in it.

The unit-disc map of :mod:`tasks.repair.chart` is a valid embedding for any chart, but it squeezes an
elongated chart (a 30 m x 3 m band of a facade) into a circle: distances along the band shrink ten
times more than across it, and a Delaunay triangulation in the disc then joins points that are metres
apart on the building with thin chords. A least-squares conformal map (LSCM, Lévy et al. 2002) keeps
angles, hence the local shape of triangles, with a free boundary. Its boundary is no longer convex, so
the triangulation is a *constrained* Delaunay triangulation (PythonCDT, the CDT library's bindings: exact
orientation and in-circle predicates) whose constraint edges are the chart's boundary edges: every border
edge is still a rebuilt edge, and nothing is triangulated outside the chart.

:func:`conformal_uv` returns None when the map folds (a face flips) or the boundary crosses itself;
:func:`constrained_triangles` returns None when the triangulation would need a point that is not given
(boundary edges that cross) or cannot be built (coincident points). The caller then falls back to the
disc map.

Frames and units: chart vertices in campus-local metres (float64); uv in metres (up to scale).
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.linalg import spsolve


def _local_frames(xyz: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each face's corners in its own plane: (m, 3) x and (m, 3) y coordinates (corner 0 at the origin)."""
    a, b, c = (xyz[faces[:, k]] for k in range(3))
    e1 = b - a
    n = np.cross(e1, c - a)
    ex = e1 / np.maximum(np.linalg.norm(e1, axis=1), 1e-18)[:, None]
    ey = np.cross(n, ex)
    ey /= np.maximum(np.linalg.norm(ey, axis=1), 1e-18)[:, None]
    x = np.c_[np.zeros(len(faces)), np.einsum("ij,ij->i", b - a, ex), np.einsum("ij,ij->i", c - a, ex)]
    y = np.c_[np.zeros(len(faces)), np.einsum("ij,ij->i", b - a, ey), np.einsum("ij,ij->i", c - a, ey)]
    return x, y


def signed_areas(uv: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m,) signed areas of the faces in uv (positive: counter-clockwise)."""
    a, b, c = (uv[faces[:, k]] for k in range(3))
    return 0.5 * ((b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]))


def _segments_cross(p: np.ndarray) -> bool:
    """Whether the closed polygon p (k, 2) has two non-adjacent edges that cross (O(k²), chunked)."""
    k = len(p)
    a, b = p, np.roll(p, -1, axis=0)
    for s in range(0, k, 256):
        i = np.arange(s, min(s + 256, k))[:, None]
        j = np.arange(k)[None, :]
        far = (np.abs(i - j) > 1) & ~((i == 0) & (j == k - 1)) & ~((j == 0) & (i == k - 1))

        def orient(p1, p2, q):
            return np.sign((p2[..., 0] - p1[..., 0]) * (q[..., 1] - p1[..., 1])
                           - (p2[..., 1] - p1[..., 1]) * (q[..., 0] - p1[..., 0]))

        ai, bi, aj, bj = a[i], b[i], a[j], b[j]
        cross = (orient(ai, bi, aj) * orient(ai, bi, bj) < 0) & (orient(aj, bj, ai) * orient(aj, bj, bi) < 0)
        if (cross & far).any():
            return True
    return False


def conformal_uv(xyz: np.ndarray, faces: np.ndarray, loop: np.ndarray) -> np.ndarray | None:
    """LSCM of a disc chart: (n, 2) float64 uv with every face counter-clockwise, or None (fold, crossing
    boundary, degenerate chart). xyz: (n, 3) float64; faces: (m, 3) int64; loop: (k,) boundary loop.

    The two loop vertices farthest apart are pinned at their 3D distance, so uv is in metres where the
    map is near-isometric (planar charts: exactly).

    >>> xyz = np.array([[0, 0, 0], [30, 0, 0], [30, 0, 3], [0, 0, 3]], float)
    >>> uv = conformal_uv(xyz, np.array([[0, 1, 2], [0, 2, 3]]), np.array([0, 1, 2, 3]))
    >>> d = lambda p: np.linalg.norm(p[:, None] - p[None], axis=-1)
    >>> bool(np.allclose(d(uv), d(xyz)))
    True
    """
    n, m = len(xyz), len(faces)
    if m == 0 or len(loop) < 3:
        return None
    x, y = _local_frames(np.asarray(xyz, np.float64), faces)
    area2 = x[:, 1] * y[:, 2] - x[:, 2] * y[:, 1]
    if (area2 <= 1e-14).any():
        return None
    wr = np.roll(x, -2, axis=1) - np.roll(x, -1, axis=1)  # W_j = p_{j+2} - p_{j+1} (as complex numbers)
    wi = np.roll(y, -2, axis=1) - np.roll(y, -1, axis=1)
    s = 1.0 / np.sqrt(area2)[:, None]
    wr, wi = wr * s, wi * s
    rows = np.repeat(np.arange(m), 3)
    cols = faces.ravel()
    # real part: sum(wr u - wi v); imaginary part: sum(wi u + wr v); unknowns [u (n), v (n)]
    r = np.r_[rows, rows, rows + m, rows + m]
    c = np.r_[cols, cols + n, cols, cols + n]
    v = np.r_[wr.ravel(), -wi.ravel(), wi.ravel(), wr.ravel()]
    a = coo_matrix((v, (r, c)), shape=(2 * m, 2 * n)).tocsc()
    p = xyz[loop]
    i0 = int(np.argmax(np.linalg.norm(p - p[0], axis=1)))  # a double sweep: nearly the loop's diameter
    i1 = int(np.argmax(np.linalg.norm(p - p[i0], axis=1)))
    pin = np.array([loop[i0], loop[i1]])
    pin_val = np.array([[0.0, 0.0], [float(np.linalg.norm(xyz[pin[1]] - xyz[pin[0]])), 0.0]])
    fixed = np.r_[pin, pin + n]
    fval = np.r_[pin_val[:, 0], pin_val[:, 1]]
    free = np.setdiff1d(np.arange(2 * n), fixed)
    af, ax = a[:, free], a[:, fixed]
    ata = (af.T @ af).tocsc()
    try:
        sol = spsolve(ata, -(af.T @ (ax @ fval)))
    except RuntimeError:
        return None
    z = np.zeros(2 * n)
    z[fixed], z[free] = fval, sol
    uv = np.c_[z[:n], z[n:]]
    if not np.isfinite(uv).all():
        return None
    sa = signed_areas(uv, faces)
    if (sa < 0).sum() > (sa > 0).sum():
        uv[:, 1] *= -1
        sa = -sa
    if (sa <= 0).any() or _segments_cross(uv[loop]):
        return None
    return uv


def constrained_triangles(uv: np.ndarray, n_loop: int) -> np.ndarray | None:
    """Constrained Delaunay triangles (t, 3) int64 of uv (q, 2), whose first n_loop rows are the chart's
    boundary polygon in order; points outside it are left out. None when the boundary crosses itself, two
    points coincide or a coordinate is not finite.

    The triangles are in a canonical order (each one's smallest index first, orientation kept, rows
    sorted): the same triangulation gives the same array, whatever order the library builds it in.

    >>> sq = np.array([[0, 0], [2, 0], [2, 2], [0, 2], [1, 1.2], [5, 5]], float)  # the last one outside
    >>> constrained_triangles(sq, 4).tolist()
    [[0, 1, 4], [0, 4, 3], [1, 2, 4], [2, 3, 4]]
    """
    import pythoncdt as cdt

    uv = np.ascontiguousarray(uv, np.float64)
    if len(uv) < 3:
        return np.zeros((0, 3), np.int64)
    if not np.isfinite(uv).all():  # the library does not check: a NaN exhausts memory
        return None
    seg = np.ascontiguousarray(np.c_[np.arange(n_loop), np.roll(np.arange(n_loop), -1)], np.uintc)
    t = cdt.Triangulation(cdt.VertexInsertionOrder.AUTO, cdt.IntersectingConstraintEdges.NOT_ALLOWED, 0.0)
    try:
        t.insert_vertices(uv)
        t.insert_edges(seg)
        t.erase_outer_triangles_and_holes()
    except (RuntimeError, ValueError, MemoryError):  # crossing boundary edges, coincident points
        return None
    if t.vertices_count() != len(uv):
        return None
    tri = np.asarray(t.triangles_array()["vertices"], np.int64).reshape(-1, 3)
    tri = np.take_along_axis(tri, (np.argmin(tri, axis=1)[:, None] + np.arange(3)) % 3, axis=1)
    q = len(uv)
    if q < (1 << 21):  # one int64 key per row, ordered like the rows (a, b, c)
        return tri[np.argsort((tri[:, 0] * q + tri[:, 1]) * q + tri[:, 2], kind="stable")]
    return tri[np.lexsort(tri.T[::-1])]


__all__ = ["conformal_uv", "constrained_triangles", "signed_areas"]
