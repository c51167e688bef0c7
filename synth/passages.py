"""Ground-floor through-passages: a rectangular tunnel from a building's front facade straight through to
the opposite facade (the thing a LoD2 city model shows as solid and a street scanner walks through).

:func:`plan_passage` picks the passage of one building (or none); :func:`passage_openings` turns it into
the wall openings :func:`synth.facades.building_mesh` cuts (the front wall's opening carries the passage's
side walls and ceiling as its reveals, the back wall's is a plain hole); :func:`in_passage` tells which
points lie in a recorded passage. The ground continues through: the terrain (``synth.terrain``) is
not cut away under a passage.

The passage is drawn from its own generator seeded by the building's id and bbox, never from the scene's
stream, so turning passages on changes nothing else in a scene but the windows and the door the passage
replaces.

Frames and units: mesh frame, metres, float64; a wall's own frame is (u along the wall from its first
footprint vertex, v up, w outward), as in :mod:`synth.facades`.
"""

from __future__ import annotations

import numpy as np

_GAP_M = 0.3  # clear wall between the passage and a window / door, and passage edge to a wall corner


def _inside(p: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Even-odd test of points p (n, 2) against polygon (k, 2) -> (n,) bool."""
    a, b = poly, np.roll(poly, -1, axis=0)
    cross = (a[:, 1] > p[:, 1:2]) != (b[:, 1] > p[:, 1:2])
    dy = np.where(b[:, 1] == a[:, 1], 1e-300, b[:, 1] - a[:, 1])
    x = a[:, 0] + (p[:, 1:2] - a[:, 1]) * (b[:, 0] - a[:, 0]) / dy
    return np.count_nonzero(cross & (p[:, :1] < x), axis=1) % 2 == 1


def _exit(fp: np.ndarray, n2: np.ndarray, front: int, u0: float, u1: float):
    """The nearest footprint edge facing away from edge ``front`` that spans [u0 - gap, u1 + gap] of it:
    (edge index, depth m) or None. fp (k, 2) CCW; n2 (k, 2) outward edge normals."""
    a, t = fp[front], (fp[(front + 1) % len(fp)] - fp[front])
    t = t / np.linalg.norm(t)
    best = None
    for j in range(len(fp)):
        if j == front or not np.allclose(n2[j], -n2[front]):
            continue
        e = np.array([fp[j], fp[(j + 1) % len(fp)]]) - a
        us, depth = np.sort(e @ t), float(-(e[0] @ n2[front]))
        if depth > 0 and us[0] <= u0 - _GAP_M and us[1] >= u1 + _GAP_M and (best is None or depth < best[1]):
            best = (j, depth)
    return best


def plan_passage(fp_params, footprint: np.ndarray, bbox, bid: int, front: int, storey_h: float) -> dict | None:
    """The passage of one building, or None (probability ``fp_params.passage_p``; no front facade; the
    front wall too short; no straight way through, as beside an L's notch).

    footprint: (k, 2) CCW axis-aligned, metres; front: index of the front edge (-1: none). Returns
    {"front_edge", "back_edge": int, "front_u", "back_u": [u0, u1] in each wall's frame, "width_m",
    "height_m", "depth_m": float, "rect": [xmin, ymin, xmax, ymax] of the passage floor}.
    """
    from .envelope import edge_normals_2d

    if fp_params.passage_p <= 0 or front < 0:
        return None
    key = np.frombuffer(np.asarray(bbox, np.float64).tobytes(), np.uint32)
    rng = np.random.default_rng([int(bid) & 0xFFFFFFFF, *key.tolist()])
    if rng.random() >= fp_params.passage_p:
        return None
    w = float(rng.uniform(*fp_params.passage_w_m))
    h = min(float(rng.uniform(*fp_params.passage_h_m)), storey_h - 0.25)
    n2 = edge_normals_2d(footprint)
    a = footprint[front]
    t = footprint[(front + 1) % len(footprint)] - a
    L = float(np.linalg.norm(t))
    t = t / L
    lo, hi = fp_params.corner_margin_m + w / 2, L - fp_params.corner_margin_m - w / 2
    if hi < lo or h < 2.2:
        return None
    for uc in [0.5 * (lo + hi), *rng.uniform(lo, hi, 7)]:
        u0, u1 = uc - w / 2, uc + w / 2
        ex = _exit(footprint, n2, front, u0, u1)
        if ex is None or ex[1] < 2 * _GAP_M:
            continue
        j, depth = ex
        s, d = np.meshgrid(np.linspace(u0 + 0.05, u1 - 0.05, 9), np.linspace(0.05, depth - 0.05, 25))
        grid = a + s.reshape(-1, 1) * t - d.reshape(-1, 1) * n2[front]
        if not _inside(grid, footprint).all():
            continue
        corners = np.array([a + u0 * t, a + u1 * t, a + u0 * t - depth * n2[front], a + u1 * t - depth * n2[front]])
        bj = footprint[j]
        tj = footprint[(j + 1) % len(footprint)] - bj
        back_u = np.sort((corners[2:] - bj) @ (tj / np.linalg.norm(tj)))
        return {"front_edge": int(front), "back_edge": int(j), "front_u": [float(u0), float(u1)],
                "back_u": [float(back_u[0]), float(back_u[1])], "width_m": w, "height_m": float(h),
                "depth_m": float(depth),
                "rect": [*map(float, corners.min(axis=0)), *map(float, corners.max(axis=0))]}
    return None


def passage_openings(passage: dict | None, edge: int, ops: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Wall ``edge``'s openings ops (k, 4) [u0, u1, v0, v1] with the passage's added and the windows /
    doors it would touch dropped. Returns (openings (k', 4), through (k',) bool, depth (k',) m: the
    passage depth on the front wall (its reveals are the passage walls and ceiling), 0 elsewhere)."""
    if passage is None or edge not in (passage["front_edge"], passage["back_edge"]):
        return ops, np.zeros(len(ops), bool), np.zeros(len(ops))
    u0, u1 = passage["front_u"] if edge == passage["front_edge"] else passage["back_u"]
    h = passage["height_m"]
    clash = (ops[:, 0] < u1 + _GAP_M) & (ops[:, 1] > u0 - _GAP_M) & (ops[:, 2] < h + _GAP_M)
    kept = ops[~clash]
    depth = passage["depth_m"] if edge == passage["front_edge"] else 0.0
    return (np.concatenate([kept, [[u0, u1, 0.0, h]]]), np.r_[np.zeros(len(kept), bool), True],
            np.r_[np.zeros(len(kept)), depth])


def in_passage(points: np.ndarray, infos: list[dict], tol: float = 1e-6) -> np.ndarray:
    """Building id (n,) int64 of the passage each point (n, 3) lies in (floor rect x [0, height]), -1 for
    none; ``infos``: ``scene.meta['buildings']`` (entries without a "passage" have none)."""
    out = np.full(len(points), -1, np.int64)
    for d in infos:
        p = d.get("passage")
        if p is None:
            continue
        r = p["rect"]
        m = ((points[:, 0] > r[0] - tol) & (points[:, 0] < r[2] + tol) & (points[:, 1] > r[1] - tol)
             & (points[:, 1] < r[3] + tol) & (points[:, 2] > -tol) & (points[:, 2] < p["height_m"] + tol))
        out[m] = d["id"]
    return out


def _clip(poly: np.ndarray, g: np.ndarray, c: float) -> np.ndarray:
    """The part of a convex planar polygon (k, 3) where ``p @ g + c >= 0`` (winding kept)."""
    f = poly @ g + c
    out = []
    for i in range(len(poly)):
        j = (i + 1) % len(poly)
        if f[i] >= -1e-9:
            out.append(poly[i])
        if (f[i] > 1e-9 and f[j] < -1e-9) or (f[i] < -1e-9 and f[j] > 1e-9):
            out.append(poly[i] + (poly[j] - poly[i]) * f[i] / (f[i] - f[j]))
    return np.array(out, float)


def passage_charts(charts: list, footprint: np.ndarray, passage: dict | None) -> list:
    """Envelope charts (``synth.envelope.Chart``) of one building with its passage opened, for a lattice
    mesh (the MVS simulator): each passage facade's wall chart cut into the pieces around the opening
    (a gable-end wall's apex triangle apart), and the passage's two side walls (kind "wall", facing into
    the passage) and ceiling (kind "soffit", EAVE) added; shared edges keep equal end points (corners at
    the opening's top are inserted where a neighbouring piece only passes by), so the lattices weld."""
    from .envelope import Chart, _oriented, edge_normals_2d, insert_points
    from .scene import FaceClass

    if passage is None:
        return list(charts)
    n2, h = edge_normals_2d(footprint), passage["height_m"]
    out, tops = [], []
    for c in charts:
        edge = next((e for e in (passage["front_edge"], passage["back_edge"]) if c.kind == "wall"
                     and np.allclose(c.normal[:2], n2[e]) and np.allclose(
                         c.polygon[:, :2].mean(0), 0.5 * (footprint[e] + footprint[(e + 1) % len(footprint)]))), None)
        if edge is None:
            out.append(c)
            continue
        a = footprint[edge]
        t2 = footprint[(edge + 1) % len(footprint)] - a
        t = np.array([*(t2 / np.linalg.norm(t2)), 0.0])
        u0, u1 = passage["front_u"] if edge == passage["front_edge"] else passage["back_u"]
        s0 = float(np.array([*a, 0.0]) @ t)

        def at(u, z, a=a, t=t):
            return np.array([*(a + u * t[:2]), z])

        H, poly = c.rect_height_m, c.polygon
        tops += [at(u0, H), at(u1, H)]
        if len(poly) == 5:  # gable end: the apex triangle stays whole, its base meets three pieces
            k = int(np.argmax(poly[:, 2]))
            tri = poly[[(k - 1) % 5, k, (k + 1) % 5]]
            out.append(Chart(insert_points(tri, np.array([at(u0, H), at(u1, H)])), c.face_class, c.kind, 0.0))
            poly = np.delete(poly, k, axis=0)
        mid = _clip(_clip(poly, t, -s0 - u0), -t, s0 + u1)
        out += [Chart(insert_points(_clip(poly, -t, s0 + u0), at(u0, h)[None]), c.face_class, "wall", H),
                Chart(insert_points(_clip(poly, t, -s0 - u1), at(u1, h)[None]), c.face_class, "wall", H),
                Chart(_clip(mid, np.array([0.0, 0.0, 1.0]), -h), c.face_class, "wall", H)]
    # the soffit along a cut wall's top meets its pieces' corners there
    out = [Chart(insert_points(c.polygon, np.array(tops)), c.face_class, c.kind, c.rect_height_m)
           if c.kind == "soffit" and tops else c for c in out]
    e = passage["front_edge"]
    a = footprint[e]
    t2 = (footprint[(e + 1) % len(footprint)] - a) / np.linalg.norm(footprint[(e + 1) % len(footprint)] - a)
    d = -passage["depth_m"] * n2[e]
    (u0, u1), z = passage["front_u"], np.zeros(4)
    for u, inward in ((u0, t2), (u1, -t2)):
        q = np.array([a + u * t2, a + u * t2 + d, a + u * t2 + d, a + u * t2])
        out.append(Chart(_oriented(np.column_stack([q, [0, 0, h, h]]), [*inward, 0.0]), FaceClass.WALL, "wall", h))
    q = np.array([a + u0 * t2, a + u1 * t2, a + u1 * t2 + d, a + u0 * t2 + d])
    out.append(Chart(_oriented(np.column_stack([q, z + h]), [0, 0, -1.0]), FaceClass.EAVE, "soffit"))
    return out
