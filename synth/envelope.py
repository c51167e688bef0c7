"""Building envelopes as planar charts: walls, eave soffits, fascias and roof planes.

The envelope is a building without its openings and protrusions. The truth mesh triangulates these
charts directly (cutting windows into the walls, see ``synth.facades``); the MVS simulator
(``synth.mvs``) covers the same charts with near-equilateral lattices and displaces the wall charts
onto the truth details. Both use these polygons, so an edge shared by two charts has the same end
points in both (the MVS lattices then conform along it).

All coordinates: mesh frame, metres, float64. A chart polygon is (k, 3), planar, wound counter-
clockwise as seen from outside (its Newell normal points out of the building).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from .scene import FaceClass

_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Chart:
    """One planar piece of an envelope.

    polygon: (k, 3) float64 metres, outward winding; kind: "wall" | "soffit" | "fascia" | "roof".
    rect_height_m: for walls, the height of the rectangular part that carries openings (gable end
    walls are pentagons whose apex rises above it); 0 otherwise.
    """

    polygon: np.ndarray
    face_class: int
    kind: str
    rect_height_m: float = 0.0

    @property
    def normal(self) -> np.ndarray:
        return polygon_normal(self.polygon)


def polygon_normal(poly: np.ndarray) -> np.ndarray:
    """Unit Newell normal of a planar polygon (k, 3) -> (3,)."""
    p, q = poly, np.roll(poly, -1, axis=0)
    n = np.array([np.sum((p[:, 1] - q[:, 1]) * (p[:, 2] + q[:, 2])),
                  np.sum((p[:, 2] - q[:, 2]) * (p[:, 0] + q[:, 0])),
                  np.sum((p[:, 0] - q[:, 0]) * (p[:, 1] + q[:, 1]))])
    return n / max(float(np.linalg.norm(n)), 1e-15)


def _oriented(poly, want) -> np.ndarray:
    poly = np.asarray(poly, dtype=np.float64)
    return poly if polygon_normal(poly) @ np.asarray(want, float) >= 0 else poly[::-1].copy()


def edge_normals_2d(fp: np.ndarray) -> np.ndarray:
    """Outward unit normals (k, 2) of the edges fp[i] -> fp[i+1] of a CCW polygon (k, 2)."""
    t = np.roll(fp, -1, axis=0) - fp
    t = t / np.linalg.norm(t, axis=1, keepdims=True)
    return np.column_stack([t[:, 1], -t[:, 0]])


def offset_orthogonal(fp: np.ndarray, d: float) -> np.ndarray:
    """Offset an axis-aligned CCW polygon (k, 2) outward by ``d`` metres (mitred corners)."""
    n = edge_normals_2d(fp)
    return fp + d * (n + np.roll(n, 1, axis=0))


def l_polygon(bbox, corner: int | None, cut_w: float = 0.0, cut_h: float = 0.0) -> np.ndarray:
    """CCW footprint (k, 2): the rectangle ``bbox`` = (x0, y0, x1, y1), minus a cut_w x cut_h
    rectangle at bbox corner ``corner`` (0: x0y0, 1: x1y0, 2: x1y1, 3: x0y1; None: no cut)."""
    x0, y0, x1, y1 = bbox
    ring = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float)
    if corner is None:
        return ring
    c = ring[corner]
    inner = c + np.sign(ring.mean(axis=0) - c) * [cut_w, cut_h]

    def on(e):  # point on the edge c -> e where the cut meets it
        step = cut_w if np.isclose(e[1], c[1]) else cut_h
        return c + (e - c) / np.linalg.norm(e - c) * step

    pts = [on(ring[corner - 1]), inner, on(ring[(corner + 1) % 4])]
    return np.array([*ring[:corner], *pts, *ring[corner + 1:]], float)


def building_charts(fp: np.ndarray, wall_h: float, roof: str, overhang: float, pitch_deg: float,
                    thickness: float) -> list[Chart]:
    """Envelope charts of one building.

    fp: (k, 2) CCW axis-aligned footprint; wall_h: wall height (m); roof: "flat" | "gable" | "hip"
    (pitched roofs need a rectangle; the ridge runs along its long axis); overhang: eave overhang
    (m, horizontal, all sides); pitch_deg: roof pitch; thickness: roof slab thickness (m, vertical).
    """
    if roof == "gable":
        return _gable_charts(fp, wall_h, overhang, np.tan(np.radians(pitch_deg)), thickness)
    tp = np.tan(np.radians(pitch_deg)) if roof == "hip" else 0.0
    n2 = edge_normals_2d(fp)
    out = offset_orthogonal(fp, overhang)
    z_e = wall_h - overhang * tp
    charts = []
    for i in range(len(fp)):
        j = (i + 1) % len(fp)
        n3 = np.array([n2[i, 0], n2[i, 1], 0.0])
        a, b, a2, b2 = fp[i], fp[j], out[i], out[j]
        charts.append(Chart(_oriented([[*a, 0], [*b, 0], [*b, wall_h], [*a, wall_h]], n3),
                            FaceClass.WALL, "wall", wall_h))
        charts.append(Chart(_oriented([[*a, wall_h], [*b, wall_h], [*b2, z_e], [*a2, z_e]], -_Z),
                            FaceClass.EAVE, "soffit"))
        charts.append(Chart(_oriented([[*a2, z_e], [*b2, z_e], [*b2, z_e + thickness], [*a2, z_e + thickness]], n3),
                            FaceClass.ROOF, "fascia"))
    top = z_e + thickness
    if roof == "flat":
        if len(out) == 4:
            charts.append(Chart(_oriented(np.column_stack([out, np.full(4, top)]), _Z), FaceClass.ROOF, "roof"))
            return charts
        # an L roof as two rectangles, split through the reflex corner; every chart edge that the split
        # point falls on gets it as a vertex, so edges shared between charts stay identical
        rects, split = _split_l(out)
        pts = np.column_stack([np.vstack([out, split]), np.full(len(out) + 1, top)])
        for r in rects:
            ring = np.array([[r[0], r[1]], [r[2], r[1]], [r[2], r[3]], [r[0], r[3]]])
            charts.append(Chart(insert_points(np.column_stack([ring, np.full(4, top)]), pts), FaceClass.ROOF, "roof"))
        return [Chart(insert_points(c.polygon, pts[-1:]), c.face_class, c.kind, c.rect_height_m)
                if c.kind == "fascia" else c for c in charts]
    swap = (out[:, 0].max() - out[:, 0].min()) < (out[:, 1].max() - out[:, 1].min())
    o = out[:, ::-1] if swap else out
    X0, Y0, X1, Y1 = o[:, 0].min(), o[:, 1].min(), o[:, 0].max(), o[:, 1].max()
    W, yc = Y1 - Y0, 0.5 * (Y0 + Y1)
    rz = top + 0.5 * W * tp
    pieces = [[[X0, Y0, top], [X1, Y0, top], [X1 - W / 2, yc, rz], [X0 + W / 2, yc, rz]],
              [[X1, Y1, top], [X0, Y1, top], [X0 + W / 2, yc, rz], [X1 - W / 2, yc, rz]],
              [[X0, Y1, top], [X0, Y0, top], [X0 + W / 2, yc, rz]],
              [[X1, Y0, top], [X1, Y1, top], [X1 - W / 2, yc, rz]]]
    for p in pieces:
        p = np.array(p)
        if swap:
            p = p[:, [1, 0, 2]]
        charts.append(Chart(_oriented(p, _Z), FaceClass.ROOF, "roof"))
    return charts


def _split_l(out: np.ndarray) -> tuple[list[list[float]], np.ndarray]:
    """Two rectangles [x0, y0, x1, y1] covering an L polygon (6, 2) CCW, split by the vertical line
    through its reflex corner; and the point (1, 2) where that line meets the opposite outer edge."""
    e1, e2 = out - np.roll(out, 1, axis=0), np.roll(out, -1, axis=0) - out
    rx, ry = out[np.argmin(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])]
    X0, Y0, X1, Y1 = out[:, 0].min(), out[:, 1].min(), out[:, 0].max(), out[:, 1].max()
    have = {(round(x, 9), round(y, 9)) for x, y in out}
    notch = next((x, y) for x in (X0, X1) for y in (Y0, Y1) if (round(x, 9), round(y, 9)) not in have)
    ylo, yhi = (Y0, ry) if np.isclose(notch[1], Y1) else (ry, Y1)
    y_opp = Y0 if np.isclose(notch[1], Y1) else Y1
    if np.isclose(notch[0], X1):
        rects = [[X0, Y0, rx, Y1], [rx, ylo, X1, yhi]]
    else:
        rects = [[rx, Y0, X1, Y1], [X0, ylo, rx, yhi]]
    return rects, np.array([[rx, y_opp]])


def insert_points(poly: np.ndarray, pts: np.ndarray, tol: float = 1e-7) -> np.ndarray:
    """Polygon (k, 3) with every point of pts (p, 3) that lies strictly inside one of its edges
    inserted there (in order along the edge)."""
    out = []
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        out.append(a)
        ab = b - a
        L2 = float(ab @ ab)
        t = (pts - a) @ ab / max(L2, 1e-18)
        off = np.linalg.norm(pts - (a + t[:, None] * ab), axis=1)
        on = (off < tol) & (t > 1e-9) & (t < 1 - 1e-9)
        out.extend(pts[on][np.argsort(t[on])])
    return np.array(out, float)


def _gable_charts(fp, H, o, tp, t) -> list[Chart]:
    """Gable roof over a rectangle; built with the ridge along x, then swapped back if needed."""
    swap = (np.ptp(fp[:, 0]) < np.ptp(fp[:, 1]))
    f = fp[:, ::-1] if swap else fp
    x0, y0, x1, y1 = f[:, 0].min(), f[:, 1].min(), f[:, 0].max(), f[:, 1].max()
    X0, Y0, X1, Y1 = x0 - o, y0 - o, x1 + o, y1 + o
    yc = 0.5 * (y0 + y1)
    zr = H + (yc - y0) * tp

    def zu(y):  # underside of the roof planes (passes through the wall tops)
        y = np.asarray(y, float)
        return H + np.where(y <= yc, y - y0, y1 - y) * tp

    def P(x, y, dz=0.0):
        return [x, y, float(zu(y)) + dz]

    raw: list[tuple[list, tuple, int, str, float]] = []  # (polygon, want, class, kind, rect_h)
    raw.append(([[x0, y0, 0], [x1, y0, 0], [x1, y0, H], [x0, y0, H]], (0, -1, 0), FaceClass.WALL, "wall", H))
    raw.append(([[x0, y1, 0], [x1, y1, 0], [x1, y1, H], [x0, y1, H]], (0, 1, 0), FaceClass.WALL, "wall", H))
    for x, s in ((x0, -1), (x1, 1)):
        raw.append(([[x, y0, 0], [x, y1, 0], [x, y1, H], [x, yc, zr], [x, y0, H]], (s, 0, 0),
                    FaceClass.WALL, "wall", H))
    xs = [X0, x0, x1, X1]
    for ya, yb, yw, s in ((Y0, y0, yc, -1), (Y1, y1, yc, 1)):  # south side, north side
        for xa, xb in itertools.pairwise(xs):  # eave strip under the long side, split at the wall ends
            raw.append(([P(xa, ya), P(xb, ya), P(xb, yb), P(xa, yb)], (0, 0, -1), FaceClass.EAVE, "soffit", 0))
            raw.append(([P(xa, ya), P(xb, ya), P(xb, ya, t), P(xa, ya, t)], (0, s, 0), FaceClass.ROOF, "fascia", 0))
        for xa, xb in ((X0, x0), (x1, X1)):  # rake soffits over the gable ends
            raw.append(([P(xa, yb), P(xb, yb), P(xb, yw), P(xa, yw)], (0, 0, -1), FaceClass.EAVE, "soffit", 0))
        for x, sx in ((X0, -1), (X1, 1)):  # rake fascias, split where the wall line crosses
            for ua, ub in ((ya, yb), (yb, yw)):
                raw.append(([P(x, ua), P(x, ub), P(x, ub, t), P(x, ua, t)], (sx, 0, 0), FaceClass.ROOF, "fascia", 0))
        top = [P(X0, ya, t), P(x0, ya, t), P(x1, ya, t), P(X1, ya, t), P(X1, yb, t), P(X1, yw, t),
               P(X0, yw, t), P(X0, yb, t)]
        raw.append((top, (0, 0, 1), FaceClass.ROOF, "roof", 0))
    charts = []
    for poly, want, cls, kind, rh in raw:
        p, w = np.array(poly, float), np.array(want, float)
        if swap:
            p, w = p[:, [1, 0, 2]], w[[1, 0, 2]]
        charts.append(Chart(_oriented(p, w), cls, kind, rh))
    return charts


def triangulate_polygon(poly: np.ndarray) -> np.ndarray:
    """Triangles (m, 3, 3) of a planar polygon that is convex or star-shaped from its reflex vertex.

    Fans from the (single) reflex vertex, else vertex 0; zero-area fan triangles (collinear
    vertices) are dropped. Winding follows the polygon's.
    """
    n = polygon_normal(poly)
    e1 = poly - np.roll(poly, 1, axis=0)
    e2 = np.roll(poly, -1, axis=0) - poly
    turn = np.cross(e1, e2) @ n
    k = int(np.argmin(turn)) if turn.min() < -1e-9 else 0
    p = np.roll(poly, -k, axis=0)
    tris = np.stack([np.repeat(p[:1], len(p) - 2, axis=0), p[1:-1], p[2:]], axis=1)
    area = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    return tris[area > 1e-9]
