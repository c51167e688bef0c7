"""Near-equilateral triangle lattices over planar charts, and small mesh operators.

``strip_chart`` covers a convex 3- or 4-cornered planar polygon with staggered rows of triangles;
its boundary samples depend only on each edge's end points and spacing, so charts sharing an edge
weld into one manifold surface. The operators (neighbour mean, vertex normals, random edge flips)
work on (n, 3) float64 vertices and (m, 3) int64 faces.
"""

from __future__ import annotations

import numpy as np

from .envelope import polygon_normal


def _edge_samples(a: np.ndarray, b: np.ndarray, h: float) -> np.ndarray:
    """Points every <= h metres on segment a-b (both (3,)), ends included exactly; the same floats
    whichever way round the segment is given (so charts sharing an edge share its samples)."""
    if tuple(np.round(b, 9)) < tuple(np.round(a, 9)):
        a, b = b, a
    n = max(1, int(np.ceil(np.linalg.norm(b - a) / h - 1e-9)))
    s = a + (b - a) * (np.arange(n + 1) / n)[:, None]
    s[-1] = b
    return s


def _chain(poly, i0, i1, edge_h) -> np.ndarray:
    """Samples along the polygon edges from vertex i0 forward to vertex i1."""
    pts, i = [], i0
    while i != i1:
        j = (i + 1) % len(poly)
        s = _edge_samples(poly[i], poly[j], edge_h[i])
        if not np.array_equal(s[0], poly[i]):
            s = s[::-1]
        pts.append(s if not pts else s[1:])
        i = j
    return np.concatenate(pts)


def _corners(poly) -> np.ndarray:
    n = polygon_normal(poly)
    e1, e2 = poly - np.roll(poly, 1, axis=0), np.roll(poly, -1, axis=0) - poly
    turn = np.cross(e1, e2) @ n / np.maximum(np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1), 1e-18)
    return np.flatnonzero(turn > 1e-7)


def _zip_rows(params: np.ndarray, prow: np.ndarray, N: int) -> np.ndarray:
    """Triangles (t, 3) joining consecutive rows 0..N of points (indices into the points), in one merge.

    params: (n,) position of each point along its row, 0..1; prow: (n,) its row, non-decreasing. Each
    segment p -> p + 1 inside a row makes one triangle with the apex in the neighbouring row, the
    segments of a row pair taken in order of their midpoints (both rows merged).
    """
    counts = np.bincount(prow, minlength=N + 1)
    row_off = np.cumsum(counts) - counts
    seg = np.flatnonzero(np.diff(prow) == 0)  # segment p -> p + 1 inside a row
    mid, srow = 0.5 * (params[seg] + params[seg + 1]), prow[seg]
    a_sel, b_sel = srow < N, srow > 0
    keys = np.concatenate([srow[a_sel] + mid[a_sel], srow[b_sel] - 1 + mid[b_sel]])
    isA = np.concatenate([np.ones(a_sel.sum(), bool), np.zeros(b_sel.sum(), bool)])
    pair = np.concatenate([srow[a_sel], srow[b_sel] - 1])
    sp_ = np.concatenate([seg[a_sel], seg[b_sel]])
    o = np.argsort(keys, kind="stable")
    isA, pair, sp_ = isA[o], pair[o], sp_[o]
    cA, cB = np.cumsum(isA) - isA, np.cumsum(~isA) - ~isA
    g = np.searchsorted(pair, pair, side="left")
    a_before, b_before = cA - cA[g], cB - cB[g]
    tri = np.where(isA[:, None],
                   np.column_stack([sp_, sp_ + 1, row_off[np.minimum(pair + 1, N)] + b_before]),
                   np.column_stack([row_off[pair] + a_before, sp_ + 1, sp_]))
    return tri


def _jitter_interior(pts: np.ndarray, tri: np.ndarray, inner: np.ndarray, n: np.ndarray, sigma: float,
                     rng: np.random.Generator) -> None:
    """Move the ``inner`` points (mask (n,)) in place by a Gaussian of std ``sigma`` in the plane of normal
    ``n``, clipped at a quarter of each point's shortest altitude, so no triangle can fold."""
    e1 = np.cross(n, [0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    t = pts[tri]
    area2 = np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)
    alt = np.full(len(pts), np.inf)
    for k in range(3):
        opp = np.linalg.norm(t[:, (k + 2) % 3] - t[:, (k + 1) % 3], axis=1)
        np.minimum.at(alt, tri[:, k], area2 / np.maximum(opp, 1e-18))
    d = rng.normal(0.0, sigma, (int(inner.sum()), 2))
    r = np.linalg.norm(d, axis=1, keepdims=True)
    d *= np.minimum(1.0, 0.25 * alt[inner][:, None] / np.maximum(r, 1e-18))
    pts[inner] += d[:, :1] * e1 + d[:, 1:] * e2


def strip_chart(poly: np.ndarray, edge_h, h: float, rng: np.random.Generator, jitter: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cover a convex planar 3- or 4-cornered polygon with staggered rows of near-equilateral triangles.

    poly: (k, 3) metres (collinear extra vertices allowed; they split sides into sub-edges);
    edge_h: (k,) sample spacing of each polygon edge (edges are sampled canonically, so two charts
    sharing an edge conform); h: spacing inside rows. Rows run parallel to the longest side, one
    per sample of the side edges; consecutive rows are zipped into triangles. Interior points get a
    tangential Gaussian jitter of ``jitter * h``, clipped at a quarter of the point's
    shortest altitude. Returns (vertices (n, 3), triangles (m, 3) int64
    wound like ``poly``, boundary (n,) bool).
    """
    c = _corners(poly)
    k = len(c)
    if k not in (3, 4):
        raise ValueError(f"strip_chart needs 3 or 4 corners, got {k}")
    side = [np.linalg.norm(poly[c[(i + 1) % k]] - poly[c[i]]) for i in range(k)]
    c = np.roll(c, -int(np.argmax(side)))
    bottom, right = _chain(poly, c[0], c[1], edge_h), _chain(poly, c[1], c[2], edge_h)
    if k == 4:
        top, left = _chain(poly, c[2], c[3], edge_h)[::-1], _chain(poly, c[3], c[0], edge_h)[::-1]
    else:
        top, left = poly[c[2]][None], _chain(poly, c[2], c[0], edge_h)[::-1]
    nl, nr = len(left) - 1, len(right) - 1
    N = max(nl, nr)
    kk = np.arange(1, N)
    Lk, Rk = left[np.rint(kk * nl / N).astype(int)], right[np.rint(kk * nr / N).astype(int)]
    m = np.maximum(1, np.rint(np.linalg.norm(Rk - Lk, axis=1) / h)).astype(int)
    odd = (kk % 2 == 1).astype(int)
    cnt = m + 1 + odd  # odd rows are staggered by half a step
    row = np.repeat(np.arange(N - 1), cnt)
    j = np.arange(cnt.sum()) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    last = j == cnt[row] - 1
    par = np.where(odd[row] == 1, np.where(j == 0, 0.0, np.where(last, 1.0, (j - 0.5) / m[row])), j / m[row])
    mid_pts = Lk[row] + par[:, None] * (Rk - Lk)[row]

    def along(p):
        span = np.linalg.norm(p[-1] - p[0])
        return np.linalg.norm(p - p[0], axis=1) / span if span > 0 else np.full(len(p), 0.5)

    pts = np.concatenate([bottom, mid_pts, top])
    params = np.concatenate([along(bottom), par, along(top)])
    prow = np.concatenate([np.zeros(len(bottom), int), row + 1, np.full(len(top), N)])
    boundary = np.concatenate([np.ones(len(bottom), bool), (j == 0) | last, np.ones(len(top), bool)])
    tri = _zip_rows(params, prow, N)
    t = pts[tri]
    cr = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    n = polygon_normal(poly)
    area = cr @ n
    tri = tri[np.abs(area) > 1e-12]
    if area.sum() < 0:
        tri = tri[:, ::-1]
    if jitter > 0:
        _jitter_interior(pts, tri, ~boundary, n, jitter * h, rng)
    return pts, tri.astype(np.int64), boundary


class NeighbourMean:
    """x -> mean of x over each vertex's edge neighbours (interior edges counted from both faces).

    faces: (m, 3) int64; n: vertex count. Works on (n,) and (n, 3) arrays.
    """

    def __init__(self, faces: np.ndarray, n: int):
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        self.src, self.dst, self.n = np.concatenate([e[:, 0], e[:, 1]]), np.concatenate([e[:, 1], e[:, 0]]), n
        self.deg = np.maximum(np.bincount(self.src, minlength=n), 1)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        if x.ndim == 1:
            return np.bincount(self.src, weights=x[self.dst], minlength=self.n) / self.deg
        return np.column_stack([self(x[:, k]) for k in range(x.shape[1])])


def random_edge_flips(vertices: np.ndarray, faces: np.ndarray, group: np.ndarray, fraction: float,
                      rng: np.random.Generator) -> np.ndarray:
    """Flip about ``fraction`` of the interior edges (between two faces of the same ``group``), each
    face at most once, where the two faces are coplanar and the flip keeps both wound the same way.

    vertices (n, 3); faces (m, 3) int64; group (m,) int. Returns new faces (m, 3); face i stays in
    place (same group), only its corners change.
    """
    m = len(faces)
    he = faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2)  # half-edges, 3 per face
    key = np.minimum(he[:, 0], he[:, 1]) * len(vertices) + np.maximum(he[:, 0], he[:, 1])
    o = np.argsort(key, kind="stable")
    pair = np.flatnonzero(key[o][1:] == key[o][:-1])
    h1, h2 = o[pair], o[pair + 1]
    f1, f2 = h1 // 3, h2 // 3
    ok = group[f1] == group[f2]
    pick = np.flatnonzero(ok)
    pick = rng.permutation(pick)[: int(fraction * len(pick))]
    h1, h2, f1, f2 = h1[pick], h2[pick], f1[pick], f2[pick]
    # each face in at most one flip: keep a flip only if it is the first to claim both its faces
    claims = np.concatenate([f1, f2])
    first = np.full(m, len(pick), np.int64)
    np.minimum.at(first, claims, np.tile(np.arange(len(pick)), 2))
    k = np.arange(len(pick))
    keep = (first[f1] == k) & (first[f2] == k)
    h1, h2, f1, f2 = h1[keep], h2[keep], f1[keep], f2[keep]
    a, b = he[h1, 0], he[h1, 1]
    c = faces[f1, (h1 % 3 + 2) % 3]
    d = faces[f2, (h2 % 3 + 2) % 3]
    t = vertices

    def normal(x, y, z):
        n = np.cross(t[y] - t[x], t[z] - t[x])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-18)

    n1, n2 = normal(a, b, c), normal(b, a, d)
    new1, new2 = normal(a, d, c), normal(d, b, c)
    cd = np.minimum(c, d) * len(vertices) + np.maximum(c, d)
    sorted_key = key[o]
    exists = sorted_key[np.minimum(np.searchsorted(sorted_key, cd), len(sorted_key) - 1)] == cd
    valid = (np.sum(n1 * n2, axis=1) > 0.999) & (np.sum(new1 * n1, axis=1) > 0.99) & \
        (np.sum(new2 * n1, axis=1) > 0.99) & ~exists
    out = faces.copy()
    out[f1[valid]] = np.column_stack([a, d, c])[valid]
    out[f2[valid]] = np.column_stack([d, b, c])[valid]
    return out
