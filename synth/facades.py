"""Truth mesh of one building: envelope charts, walls cut by windows and doors (recessed glass, frame
reveals), balconies and ledges.

Frames and units: mesh frame, metres, float64, z up; a wall's own frame is (t along the wall, z up, n
outward).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .envelope import building_charts, edge_normals_2d, triangulate_polygon
from .passages import passage_openings, plan_passage
from .scene import CLASS_COLOR, Building, FaceClass, Mesh, soup_to_mesh

_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class FacadeParams:
    """Openings and protrusions on walls."""

    column_pitch_m: tuple[float, float] = (2.6, 4.0)
    window_w_m: tuple[float, float] = (1.0, 1.8)
    window_h_m: tuple[float, float] = (1.2, 1.8)
    sill_m: tuple[float, float] = (0.8, 1.0)
    recess_m: tuple[float, float] = (0.1, 0.3)  # glass behind the wall plane
    door_w_m: tuple[float, float] = (1.2, 2.0)
    door_h_m: tuple[float, float] = (2.2, 2.5)
    corner_margin_m: float = 0.8  # wall corner -> nearest opening
    blank_column_p: float = 0.1
    style_p: tuple[float, float, float] = (0.45, 0.3, 0.25)  # balconies, ledges, plain
    balcony_p: float = 0.3  # per window column and storey line
    balcony_depth_m: tuple[float, float] = (0.8, 1.5)
    ledge_depth_m: tuple[float, float] = (0.12, 0.3)
    passage_p: float = 0.0  # per building: a ground-floor through-passage from the front facade (synth.passages)
    passage_w_m: tuple[float, float] = (3.0, 5.0)
    passage_h_m: tuple[float, float] = (3.0, 4.0)  # clamped to the ground storey (storey height - 0.25 m)


def _wall_frame(a2, b2):
    t = np.array([b2[0] - a2[0], b2[1] - a2[1], 0.0])
    L = float(np.linalg.norm(t))
    t /= L
    return np.array([a2[0], a2[1], 0.0]), t, np.array([t[1], -t[0], 0.0]), L


def _quads(P0, t, n, U, V, W, want) -> np.ndarray:
    """Quads given in wall coordinates (q, 4) each -> triangles (2q, 3, 3) wound towards ``want`` (q, 3)."""
    c = P0 + U[..., None] * t + V[..., None] * _Z + W[..., None] * n
    nrm = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    flip = np.sum(nrm * want, axis=1) < 0
    c[flip] = c[flip][:, ::-1]
    return np.concatenate([c[:, [0, 1, 2]], c[:, [0, 2, 3]]])


def _wall_with_openings(P0, t, n, L, H, openings, recess, through=None):
    """Wall rectangle [0, L] x [0, H] with rectangular openings (k, 4) [u0, u1, v0, v1].

    The wall is a grid of quads around the openings; each opening has a GLASS pane ``recess`` m
    behind the wall plane and FRAME reveals. An opening flagged in ``through`` (k,) bool is a passage:
    no pane; where its ``recess`` is > 0 its reveals that deep are the passage's WALL sides and EAVE
    ceiling (no floor: the terrain runs through). Returns {FaceClass: triangles (m, 3, 3)}.
    """
    ub = np.unique(np.concatenate([[0.0, L], openings[:, :2].ravel()]))
    vb = np.unique(np.concatenate([[0.0, H], openings[:, 2:].ravel()]))
    uc, vc = 0.5 * (ub[:-1] + ub[1:]), 0.5 * (vb[:-1] + vb[1:])
    ins = ((uc[:, None, None] > openings[:, 0]) & (uc[:, None, None] < openings[:, 1])
           & (vc[None, :, None] > openings[:, 2]) & (vc[None, :, None] < openings[:, 3]))
    cell = np.full(ins.shape[:2], -1)  # (nu, nv) opening index or -1
    if len(openings):
        cell = np.where(ins.any(axis=2), ins.argmax(axis=2), -1)
    I, J = np.meshgrid(np.arange(len(uc)), np.arange(len(vc)), indexing="ij")
    out = {}

    def cells(mask, w):  # w: (k,) depth of each selected cell
        i, j = I[mask], J[mask]
        U = np.stack([ub[i], ub[i + 1], ub[i + 1], ub[i]], 1)
        V = np.stack([vb[j], vb[j], vb[j + 1], vb[j + 1]], 1)
        return _quads(P0, t, n, U, V, np.repeat(w[:, None], 4, axis=1), np.broadcast_to(n, (len(i), 3)))

    out[FaceClass.WALL] = cells(cell < 0, np.zeros(int((cell < 0).sum())))
    thr = np.zeros(len(openings), bool) if through is None else np.asarray(through, bool)
    thr_cell = (cell >= 0) & thr[np.maximum(cell, 0)] if len(openings) else np.zeros(cell.shape, bool)
    op = (cell >= 0) & ~thr_cell
    out[FaceClass.GLASS] = cells(op, -recess[cell[op]])
    pad = np.pad(cell, 1, constant_values=-2)
    reveals = []
    tunnel = {FaceClass.WALL: [], FaceClass.EAVE: []}
    for di, dj, want in ((-1, 0, t), (1, 0, -t), (0, -1, _Z), (0, 1, -_Z)):
        nb = pad[1 + di:pad.shape[0] - 1 + di, 1 + dj:pad.shape[1] - 1 + dj]
        if dj >= 0 and thr_cell.any():  # passage sides and ceiling (the floor, dj < 0, is terrain)
            i, j = I[thr_cell & (nb != cell)], J[thr_cell & (nb != cell)]
            tunnel[FaceClass.WALL if di else FaceClass.EAVE].append(
                _reveal_quads(P0, t, n, ub, vb, i, j, di, dj, -recess[cell[i, j]], want))
        m = op & (nb != cell)
        reveals.append(_reveal_quads(P0, t, n, ub, vb, I[m], J[m], di, dj, -recess[cell[m]], want))
    out[FaceClass.FRAME] = np.concatenate(reveals)
    for cls, lst in tunnel.items():
        tris = np.concatenate(lst) if lst else np.zeros((0, 3, 3))
        tris = tris[0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1) > 1e-9]
        if len(tris):
            out[cls] = np.concatenate([out[cls], tris]) if cls in out else tris
    return out


def _reveal_quads(P0, t, n, ub, vb, i, j, di, dj, r, want) -> np.ndarray:
    """Reveal quads of grid cells (i, j) on side (di, dj), from the wall plane to depth r (k,) (< 0: behind)."""
    if di:
        u = ub[i] if di < 0 else ub[i + 1]
        U, V = np.stack([u, u, u, u], 1), np.stack([vb[j], vb[j + 1], vb[j + 1], vb[j]], 1)
    else:
        v = vb[j] if dj < 0 else vb[j + 1]
        U, V = np.stack([ub[i], ub[i + 1], ub[i + 1], ub[i]], 1), np.stack([v, v, v, v], 1)
    W = np.stack([np.zeros_like(r), np.zeros_like(r), r, r], 1)
    return _quads(P0, t, n, U, V, W, np.broadcast_to(want, (len(i), 3)))


def _box(P0, t, n, u, v, w, omit=("back",)) -> np.ndarray:
    """Axis-aligned box in wall coordinates (ranges u, v, w) -> triangles, outward, minus ``omit`` sides."""
    (u0, u1), (v0, v1), (w0, w1) = u, v, w
    sides = {"front": ([u0, u1, u1, u0], [v0, v0, v1, v1], [w1] * 4, n),
             "back": ([u0, u1, u1, u0], [v0, v0, v1, v1], [w0] * 4, -n),
             "left": ([u0] * 4, [v0, v1, v1, v0], [w0, w0, w1, w1], -t),
             "right": ([u1] * 4, [v0, v1, v1, v0], [w0, w0, w1, w1], t),
             "bottom": ([u0, u1, u1, u0], [v0] * 4, [w0, w0, w1, w1], -_Z),
             "top": ([u0, u1, u1, u0], [v1] * 4, [w0, w0, w1, w1], _Z)}
    keep = [sides[k] for k in sides if k not in omit]
    U, V, W, want = (np.array([k[i] for k in keep], float) for i in range(4))
    return _quads(P0, t, n, U, V, W, want)


def _facade_layout(rng, L, storeys, sh, fp: FacadeParams, bp: dict, is_front: bool):
    """Openings (k, 4) [u0, u1, v0, v1] and window column centres of one wall of length L."""
    pitch, ww, wh, sill = bp["pitch"], bp["ww"], bp["wh"], bp["sill"]
    span = L - 2 * fp.corner_margin_m - ww
    ncol = int(np.floor(span / pitch)) + 1 if span >= 0 else 0
    cols = L / 2 + (np.arange(ncol) - (ncol - 1) / 2) * pitch
    cols = cols[rng.random(ncol) >= fp.blank_column_p]
    s = np.arange(storeys)
    ops = [np.column_stack([np.repeat(cols - ww / 2, storeys), np.repeat(cols + ww / 2, storeys),
                            np.tile(s * sh + sill, len(cols)), np.tile(s * sh + sill + wh, len(cols))])]
    if is_front and L >= bp["dw"] + 2 * fp.corner_margin_m:
        uc = cols[np.argmin(np.abs(cols - L / 2))] if len(cols) else L / 2
        uc = float(np.clip(uc, fp.corner_margin_m + bp["dw"] / 2, L - fp.corner_margin_m - bp["dw"] / 2))
        door = np.array([[uc - bp["dw"] / 2, uc + bp["dw"] / 2, 0.0, bp["dh"]]])
        o = ops[0]
        clash = (o[:, 0] < door[0, 1]) & (o[:, 1] > door[0, 0]) & (o[:, 2] < door[0, 3])
        ops = [o[~clash], door]
    return np.concatenate(ops), cols


def building_mesh(rng, b: Building, info: dict, fp: FacadeParams, wall_rgb, roof_rgb) -> Mesh:
    """Truth mesh of one building from its record and its ``meta['buildings']`` entry ``info``; a
    through-passage (``fp.passage_p``, :mod:`synth.passages`) is recorded as ``info["passage"]``."""
    charts = building_charts(b.footprint, b.height_m, b.roof, b.eave_overhang_m, info["pitch_deg"],
                             info["roof_thickness_m"])
    soup: dict[int, list] = {c: [] for c in FaceClass}
    normals2 = edge_normals_2d(b.footprint)
    front = info["front_normal"]
    front_edges = [i for i in range(len(normals2)) if front is not None and np.allclose(normals2[i], front)]
    front_edge = max(front_edges, key=lambda i: np.linalg.norm(b.footprint[(i + 1) % len(b.footprint)]
                                                               - b.footprint[i])) if front_edges else -1
    walls = [c for c in charts if c.kind == "wall"]
    for c in charts:
        if c.kind != "wall":
            soup[c.face_class].append(triangulate_polygon(c.polygon))
    sh, H = b.storey_height_m, b.height_m
    passage = plan_passage(fp, b.footprint, info["bbox"], b.id, front_edge, sh)
    if passage is not None:
        info["passage"] = passage
    for i in range(len(b.footprint)):
        a2, b2 = b.footprint[i], b.footprint[(i + 1) % len(b.footprint)]
        P0, t, n, L = _wall_frame(a2, b2)
        ops, cols = _facade_layout(rng, L, b.storeys, sh, fp, info["_bp"], i == front_edge)
        ops, through, depth = passage_openings(passage, i, ops)
        rec = np.where(through, depth, info["recess_m"])
        for cls, tris in _wall_with_openings(P0, t, n, L, H, ops, rec, through).items():
            soup[cls].append(tris)
        poly = next(w.polygon for w in walls if np.allclose(w.polygon[:, :2].mean(0), (a2 + b2) / 2)
                    and np.allclose(w.normal, n))
        if len(poly) == 5:  # gable apex above the rectangular part
            soup[FaceClass.WALL].append(triangulate_polygon(poly[poly[:, 2] >= H - 1e-9]))
        if info["style"] == "balcony" and len(cols):
            dep, bw = info["protrusion_m"], min(info["_bp"]["ww"] + 0.6, info["_bp"]["pitch"] - 0.3)
            k, j = np.nonzero(rng.random((b.storeys - 1, len(cols))) < fp.balcony_p)
            for kk, jj in zip(k + 1, j):
                u = (cols[jj] - bw / 2, cols[jj] + bw / 2)
                soup[FaceClass.BALCONY].append(_box(P0, t, n, u, (kk * sh - 0.2, kk * sh), (0.0, dep)))
                soup[FaceClass.BALCONY].append(_box(P0, t, n, u, (kk * sh, kk * sh + 1.0), (dep - 0.08, dep),
                                                    omit=("bottom",)))
        elif info["style"] == "ledge" and L > 2 * info["protrusion_m"] + 1.0:
            d = info["protrusion_m"]
            for kk in range(1, b.storeys):
                soup[FaceClass.BALCONY].append(_box(P0, t, n, (d, L - d), (kk * sh - 0.15, kk * sh), (0.0, d)))
    colors = {FaceClass.WALL: wall_rgb, FaceClass.ROOF: roof_rgb}
    parts = []
    for cls, lst in soup.items():
        if lst:
            tris = np.concatenate(lst)
            rgb = colors.get(cls, jitter_colour(rng, CLASS_COLOR[cls], 8))
            parts.append((tris, cls, rgb))
    return soup_to_mesh(parts, b.id)


def jitter_colour(rng, rgb, amount) -> np.ndarray:
    """``rgb`` plus uniform noise in [-amount, amount] per channel, as (3,) uint8."""
    return np.clip(np.asarray(rgb, float) + rng.uniform(-amount, amount, 3), 0, 255).astype(np.uint8)
