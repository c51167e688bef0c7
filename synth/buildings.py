"""Synthetic campus truth: a road grid, terrain and buildings with windows, doors, balconies and eaves.

Roads lie on a *global* grid (``LayoutParams.road_spacing_m``, offset and widths derived from the
road index only), so a campus generated tile by tile (``make_scene(..., extent=tile)``) has roads
that line up across tile borders; buildings are placed only where they fit entirely in the extent.

Frames and units: mesh frame, metres, float64, z up, terrain at z = 0 (roads at ``road_z_m``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .envelope import Chart, building_charts, edge_normals_2d, l_polygon, triangulate_polygon
from .scene import CLASS_COLOR, Building, FaceClass, Mesh, Occluders, Scene

_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class LayoutParams:
    """Campus layout. Ranges are (low, high), sampled uniformly."""

    road_spacing_m: float = 120.0  # global road grid pitch (both axes)
    road_offset_m: float = 50.0  # road centre lines at offset + i * spacing
    road_width_m: tuple[float, float] = (7.0, 10.0)  # per road, a function of the road index only
    road_seed: int = 0
    road_z_m: float = 0.02
    facade_from_centre_m: tuple[float, float] = (4.0, 15.0)  # front facade to road centre line
    sidewalk_min_m: float = 2.5  # minimum road edge -> facade distance
    side_m: tuple[float, float] = (10.0, 40.0)
    storey_height_m: tuple[float, float] = (3.0, 3.5)
    eave_overhang_m: tuple[float, float] = (0.3, 1.2)
    pitch_deg: tuple[float, float] = (20.0, 40.0)
    roof_thickness_m: tuple[float, float] = (0.2, 0.3)
    roof_p: tuple[float, float, float] = (0.5, 0.25, 0.25)  # flat, gable, hip (pitched: rectangles only)
    l_shape_p: float = 0.35
    gap_m: float = 6.0  # minimum clear gap between buildings' outermost parts
    tries_per_building: int = 80


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


def road_lines(extent, layout: LayoutParams = LayoutParams()) -> list[tuple[int, float, float]]:
    """Roads whose surface meets ``extent``: (axis, centre, half_width) with axis 0 = road along y at
    x = centre, axis 1 = road along x at y = centre. Depends only on the global grid, not on a seed."""
    out = []
    for axis in (0, 1):
        lo, hi = extent[axis], extent[axis + 2]
        hw_max = 0.5 * layout.road_width_m[1]
        i0 = int(np.ceil((lo - hw_max - layout.road_offset_m) / layout.road_spacing_m))
        i1 = int(np.floor((hi + hw_max - layout.road_offset_m) / layout.road_spacing_m))
        for i in range(i0, i1 + 1):
            c = layout.road_offset_m + i * layout.road_spacing_m
            r = np.random.default_rng([layout.road_seed, axis, i + (1 << 30)])
            hw = 0.5 * float(r.uniform(*layout.road_width_m))
            if c + hw > lo and c - hw < hi:
                out.append((axis, float(c), hw))
    return out


def _intervals(lo, hi, roads):
    """Free intervals between road strips along one axis: (a, b, road_below, road_above)."""
    out, start, below = [], lo, None
    for c, hw in sorted(roads):
        if c - hw > start:
            out.append((start, c - hw, below, (c, hw)))
        start, below = max(start, c + hw), (c, hw)
    if hi > start:
        out.append((start, hi, below, None))
    return out


def _place_footprints(rng, extent, n, roads, layout: LayoutParams, margins: list[float]):
    """Rejection-sample building bboxes in the blocks between roads.

    Returns a list of (bbox (4,), front_normal (2,) or None, keep_out (4,)); ``margins[k]`` is the
    k-th building's protrusion (eaves/balconies) beyond its walls.
    """
    iv = [_intervals(extent[a], extent[a + 2], [(c, hw) for ax, c, hw in roads if ax == a]) for a in (0, 1)]
    blocks = [(bx, by) for bx in iv[0] for by in iv[1]]
    weights = np.array([(bx[1] - bx[0]) * (by[1] - by[0]) for bx, by in blocks])
    placed = []
    for k in range(n):
        m = margins[k]
        for _ in range(layout.tries_per_building):
            bx, by = blocks[rng.choice(len(blocks), p=weights / weights.sum())]
            blk = (bx, by)
            sides = [(a, s) for a in (0, 1) for s in (0, 1) if blk[a][2 + s] is not None]
            along, depth = rng.uniform(*layout.side_m, size=2)
            lo_hi = []
            for a in (0, 1):  # clear ranges per axis: sidewalk from a road, margin from the extent
                a0, a1, rb, ra = blk[a]
                lo_hi.append((a0 + (layout.sidewalk_min_m if rb else m), a1 - (layout.sidewalk_min_m if ra else m)))
            size, front = np.array([along, depth]), None
            if sides:
                a, s = sides[rng.integers(len(sides))]
                c, hw = blk[a][2 + s]
                d = rng.uniform(max(layout.facade_from_centre_m[0], hw + layout.sidewalk_min_m),
                                max(layout.facade_from_centre_m[1], hw + layout.sidewalk_min_m))
                size = np.array([depth, along]) if a == 0 else np.array([along, depth])
                lo = np.array([0.0, 0.0])
                lo[a] = c + d if s == 0 else c - d - size[a]
                b = 1 - a
                lo[b] = rng.uniform(lo_hi[b][0], max(lo_hi[b][0], lo_hi[b][1] - size[b]))
                front = np.zeros(2)
                front[a] = -1.0 if s == 0 else 1.0
            else:
                lo = np.array([rng.uniform(lo_hi[a][0], max(lo_hi[a][0], lo_hi[a][1] - size[a])) for a in (0, 1)])
            bbox = np.array([lo[0], lo[1], lo[0] + size[0], lo[1] + size[1]])
            if any(bbox[a] < lo_hi[a][0] - 1e-9 or bbox[a + 2] > lo_hi[a][1] + 1e-9 for a in (0, 1)):
                continue
            keep = bbox + np.array([-1, -1, 1, 1]) * (m + 0.5 * layout.gap_m)
            if any(keep[0] < q[2] and q[0] < keep[2] and keep[1] < q[3] and q[1] < keep[3] for _, _, q in placed):
                continue
            placed.append((bbox, front, keep))
            break
    return placed


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


def _wall_with_openings(P0, t, n, L, H, openings, recess):
    """Wall rectangle [0, L] x [0, H] with rectangular openings (k, 4) [u0, u1, v0, v1].

    The wall is a grid of quads around the openings; each opening has a GLASS pane ``recess`` m
    behind the wall plane and FRAME reveals. Returns {FaceClass: triangles (m, 3, 3)}.
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
    op = cell >= 0
    out[FaceClass.GLASS] = cells(op, -recess[cell[op]])
    pad = np.pad(cell, 1, constant_values=-2)
    reveals = []
    for di, dj, want in ((-1, 0, t), (1, 0, -t), (0, -1, _Z), (0, 1, -_Z)):
        nb = pad[1 + di:pad.shape[0] - 1 + di, 1 + dj:pad.shape[1] - 1 + dj]
        m = op & (nb != cell)
        i, j = I[m], J[m]
        r = -recess[cell[m]]
        if di:
            u = ub[i] if di < 0 else ub[i + 1]
            U, V = np.stack([u, u, u, u], 1), np.stack([vb[j], vb[j + 1], vb[j + 1], vb[j]], 1)
        else:
            v = vb[j] if dj < 0 else vb[j + 1]
            U, V = np.stack([ub[i], ub[i + 1], ub[i + 1], ub[i]], 1), np.stack([v, v, v, v], 1)
        W = np.stack([np.zeros_like(r), np.zeros_like(r), r, r], 1)
        reveals.append(_quads(P0, t, n, U, V, W, np.broadcast_to(want, (len(i), 3))))
    out[FaceClass.FRAME] = np.concatenate(reveals)
    return out


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
    """Truth mesh of one building from its record and its ``meta['buildings']`` entry ``info``."""
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
    for i in range(len(b.footprint)):
        a2, b2 = b.footprint[i], b.footprint[(i + 1) % len(b.footprint)]
        P0, t, n, L = _wall_frame(a2, b2)
        ops, cols = _facade_layout(rng, L, b.storeys, sh, fp, info["_bp"], i == front_edge)
        rec = np.full(len(ops), info["recess_m"])
        for cls, tris in _wall_with_openings(P0, t, n, L, H, ops, rec).items():
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
            rgb = colors.get(cls, _jitter(rng, CLASS_COLOR[cls], 8))
            parts.append((tris, cls, rgb))
    return soup_to_mesh(parts, b.id)


def _jitter(rng, rgb, amount) -> np.ndarray:
    return np.clip(np.asarray(rgb, float) + rng.uniform(-amount, amount, 3), 0, 255).astype(np.uint8)


def soup_to_mesh(parts, building: int, tol: float = 1e-6) -> Mesh:
    """[(triangles (m, 3, 3), class, rgb (3,)), ...] -> welded Mesh (vertices merged within ``tol`` m)."""
    tris = np.concatenate([p[0] for p in parts])
    key = np.round(tris.reshape(-1, 3) / tol).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return Mesh(vertices=tris.reshape(-1, 3)[first], faces=inv.reshape(-1, 3).astype(np.int64),
                face_class=np.concatenate([np.full(len(p[0]), p[1], np.uint8) for p in parts]),
                face_building=np.full(len(tris), building, np.int32),
                face_color=np.concatenate([np.tile(np.asarray(p[2], np.uint8), (len(p[0]), 1)) for p in parts]))


def terrain_cells(extent, roads, infos: list[dict]):
    """The terrain grid: cell bounds xs (nx + 1,), ys (ny + 1,) cut at road edges and building bbox /
    notch lines; road (nx, ny) bool: cell on a road; inside (nx, ny) bool: cell under a building."""
    x0, y0, x1, y1 = extent
    br = [r for inf in infos for r in [inf["bbox"]] + ([inf["cut"]] if inf["cut"] is not None else [])]
    cuts = [[], []]
    for ax, c, hw in roads:
        cuts[ax] += [c - hw, c + hw]
    for r in br:
        cuts[0] += [r[0], r[2]]
        cuts[1] += [r[1], r[3]]
    xs = np.unique(np.clip([x0, x1, *cuts[0]], x0, x1))
    ys = np.unique(np.clip([y0, y1, *cuts[1]], y0, y1))
    cx, cy = np.meshgrid(0.5 * (xs[:-1] + xs[1:]), 0.5 * (ys[:-1] + ys[1:]), indexing="ij")
    road = np.zeros(cx.shape, bool)
    for ax, c, hw in roads:
        road |= np.abs((cx if ax == 0 else cy) - c) < hw
    inside = np.zeros(cx.shape, bool)
    for inf in infos:
        bx = inf["bbox"]
        m = (cx > bx[0]) & (cx < bx[2]) & (cy > bx[1]) & (cy < bx[3])
        if inf["cut"] is not None:
            q = inf["cut"]
            m &= ~((cx > q[0]) & (cx < q[2]) & (cy > q[1]) & (cy < q[3]))
        inside |= m
    return xs, ys, road, inside


def terrain_mesh(extent, roads, infos: list[dict], road_z_m: float) -> Mesh:
    """GROUND and ROAD quads on the ``terrain_cells`` grid (no terrain under buildings).
    roads: [(axis, centre, half_width)]."""
    xs, ys, road, inside = terrain_cells(extent, roads, infos)
    I, J = np.meshgrid(np.arange(len(xs) - 1), np.arange(len(ys) - 1), indexing="ij")
    parts = []
    for cls, mask, z in ((FaceClass.GROUND, ~road & ~inside, 0.0), (FaceClass.ROAD, road & ~inside, road_z_m)):
        i, j = I[mask], J[mask]
        q = np.stack([np.stack([xs[i], ys[j]], 1), np.stack([xs[i + 1], ys[j]], 1),
                      np.stack([xs[i + 1], ys[j + 1]], 1), np.stack([xs[i], ys[j + 1]], 1)], 1)
        q = np.concatenate([q, np.full(q.shape[:2] + (1,), z)], axis=2)
        if len(q):
            parts.append((np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]]), cls, CLASS_COLOR[cls]))
    return soup_to_mesh(parts, -1)


def _building_record(rng, bid, bbox, front, storeys, layout: LayoutParams, fp: FacadeParams, style, margin, overhang):
    dims = bbox[2:] - bbox[:2]
    corner, cw, ch = None, 0.0, 0.0
    if min(dims) >= 16 and rng.random() < layout.l_shape_p:
        ring = np.array([[bbox[0], bbox[1]], [bbox[2], bbox[1]], [bbox[2], bbox[3]], [bbox[0], bbox[3]]])
        score = ring @ front if front is not None else rng.random(4)
        corner = int(rng.choice(np.argsort(score)[:2]))
        cw, ch = rng.uniform(0.35, 0.6, 2) * dims
        cw, ch = min(cw, dims[0] - 6), min(ch, dims[1] - 6)
    fpoly = l_polygon(bbox, corner, cw, ch)
    cut = None
    if corner is not None:
        c = fpoly[corner + 1]  # the inner (reflex) vertex
        k = np.array([[bbox[0], bbox[1]], [bbox[2], bbox[1]], [bbox[2], bbox[3]], [bbox[0], bbox[3]]])[corner]
        cut = [min(c[0], k[0]), min(c[1], k[1]), max(c[0], k[0]), max(c[1], k[1])]
    n = int(rng.integers(storeys[0], storeys[1] + 1))
    sh = float(rng.uniform(*layout.storey_height_m))
    roof = str(rng.choice(["flat", "gable", "hip"], p=np.array(layout.roof_p) / sum(layout.roof_p)))
    if corner is not None or max(dims) / min(dims) < 1.15:
        roof = "flat"
    wh = min(float(rng.uniform(*fp.window_h_m)), sh - fp.sill_m[1] - 0.4)
    pitch = float(rng.uniform(*fp.column_pitch_m))
    bp = {"pitch": pitch, "ww": min(float(rng.uniform(*fp.window_w_m)), pitch - 0.8), "wh": wh,
          "sill": float(rng.uniform(*fp.sill_m)), "dw": min(float(rng.uniform(*fp.door_w_m)), pitch - 0.6),
          "dh": min(float(rng.uniform(*fp.door_h_m)), sh - 0.4)}
    b = Building(id=bid, footprint=fpoly, storeys=n, storey_height_m=sh, roof=roof, eave_overhang_m=overhang,
                 height_m=n * sh)
    thick = float(rng.uniform(*layout.roof_thickness_m))
    pitch_deg = float(rng.uniform(*layout.pitch_deg)) if roof != "flat" else 0.0
    tp = np.tan(np.radians(pitch_deg))
    top = n * sh + thick + (0.5 * min(dims) * tp if roof != "flat" else 0.0)
    info = {"id": bid, "bbox": [float(v) for v in bbox], "cut": cut, "roof": roof, "pitch_deg": pitch_deg,
            "roof_thickness_m": thick, "overhang_m": overhang, "wall_height_m": n * sh, "storey_height_m": sh,
            "eave_z_m": n * sh - overhang * (tp if roof == "hip" or roof == "gable" else 0.0),
            "top_z_m": float(top), "recess_m": float(rng.uniform(*fp.recess_m)), "style": style,
            "protrusion_m": margin, "front_normal": None if front is None else [float(v) for v in front],
            "_bp": bp}
    return b, info


def make_scene(rng: np.random.Generator, extent: tuple[float, float, float, float], n_buildings: int,
               storeys: tuple[int, int] = (1, 12), layout: LayoutParams = LayoutParams(),
               facade: FacadeParams = FacadeParams(), occluder_density: float = 1.0,
               first_building_id: int = 0, first_occluder_id: int = 0) -> Scene:
    """A synthetic campus (or one tile of it): terrain, roads, up to ``n_buildings`` buildings, occluders.

    extent: (xmin, ymin, xmax, ymax) metres, campus-local; every building (with its eaves and
    balconies) and every occluder lies inside it; road surfaces and terrain are clipped to it, road
    centre lines are listed when the centre lies in [min, max) (so tiles do not list a road twice).
    storeys: inclusive range. Building ids start at ``first_building_id`` (unique across tiles when
    the caller offsets them). Deterministic in ``rng``.

    scene.meta: "buildings": per-building dicts (bbox, cut, roof, pitch_deg, roof_thickness_m,
    overhang_m, wall_height_m, eave_z_m, top_z_m, recess_m, style, protrusion_m, front_normal);
    "roads": [(axis, centre, half_width)]; "cars", "occluders": see ``synth.occluders``;
    "n_requested": n_buildings.
    """
    from .occluders import make_occluders

    extent = tuple(float(v) for v in extent)
    roads = road_lines(extent, layout)
    plan = []
    for _ in range(n_buildings):
        style = str(rng.choice(["balcony", "ledge", "plain"], p=np.array(facade.style_p) / sum(facade.style_p)))
        prot = {"balcony": float(rng.uniform(*facade.balcony_depth_m)),
                "ledge": float(rng.uniform(*facade.ledge_depth_m)), "plain": 0.0}[style]
        plan.append((style, prot, float(rng.uniform(*layout.eave_overhang_m))))
    placed = _place_footprints(rng, extent, n_buildings, roads, layout, [max(p[1], p[2]) + 0.05 for p in plan])
    buildings, infos, meshes = [], [], []
    for k, (bbox, front, _) in enumerate(placed):
        style, prot, overhang = plan[k]
        b, info = _building_record(rng, first_building_id + k, bbox, front, storeys, layout, facade, style, prot,
                                   overhang)
        wall_rgb = _jitter(rng, CLASS_COLOR[FaceClass.WALL], 40)
        roof_rgb = _jitter(rng, CLASS_COLOR[FaceClass.ROOF], 25)
        meshes.append(building_mesh(rng, b, info, facade, wall_rgb, roof_rgb))
        info.pop("_bp")
        buildings.append(b)
        infos.append(info)
    truth = Mesh.concat([terrain_mesh(extent, roads, infos, layout.road_z_m)] + meshes)
    polylines, meta_roads = [], []
    for ax, c, hw in roads:
        meta_roads.append([ax, c, hw])
        if extent[ax] <= c < extent[ax + 2]:
            b = 1 - ax
            line = np.zeros((2, 2))
            line[:, ax] = c
            line[:, b] = [extent[b], extent[b + 2]]
            polylines.append(line)
    scene = Scene(truth=truth, occluders=Occluders(Mesh.empty()), buildings=buildings, roads=polylines,
                  extent=extent, meta={"buildings": infos, "roads": meta_roads, "n_requested": int(n_buildings),
                                       "layout": asdict(layout)})
    scene.occluders = make_occluders(rng, scene, density=occluder_density, first_id=first_occluder_id)
    return scene


def charts_of(scene: Scene) -> dict[int, list[Chart]]:
    """Envelope charts per building id, rebuilt from the scene's records (used by the MVS simulator)."""
    info = {d["id"]: d for d in scene.meta["buildings"]}
    return {b.id: building_charts(b.footprint, b.height_m, b.roof, b.eave_overhang_m, info[b.id]["pitch_deg"],
                                  info[b.id]["roof_thickness_m"]) for b in scene.buildings}
