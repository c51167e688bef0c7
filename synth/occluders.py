"""Street furniture in front of facades: trees, parked cars, pedestrians and fences.

The MLS scan and the cameras see them; the truth excludes them. Every occluder is kept clear of
every building (its walls, and its eaves and balconies above the height where they start) by an
axis-aligned box test, stays inside the scene extent, and does not touch another occluder.

Frames and units: mesh frame, metres, float64, z up.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .scene import Mesh, OccluderClass, Occluders, Scene


@dataclass(frozen=True)
class OccluderParams:
    """Rates are per 100 m of road side, multiplied by ``make_occluders(density=...)``."""

    trees_per_100m: float = 6.0
    cars_per_100m: float = 7.0
    pedestrians_per_100m: float = 4.0
    fence_p: float = 0.35  # per building: a fence along part of its front facade
    tree_height_m: tuple[float, float] = (4.0, 10.0)
    crown_radius_m: tuple[float, float] = (1.2, 3.0)
    tree_from_curb_m: tuple[float, float] = (1.0, 2.2)
    car_length_m: tuple[float, float] = (4.2, 4.8)
    car_width_m: tuple[float, float] = (1.7, 1.9)
    car_height_m: tuple[float, float] = (1.4, 1.6)
    car_centre_from_curb_m: tuple[float, float] = (1.0, 1.4)  # parking lane at the road edge
    pedestrian_from_curb_m: tuple[float, float] = (0.4, 4.0)
    fence_height_m: tuple[float, float] = (1.2, 2.0)
    fence_from_facade_m: tuple[float, float] = (0.8, 1.6)
    crossing_clear_m: float = 6.0  # no occluder this close to a crossing road's edge


_HEX_FACES = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                       [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def hexahedron(bottom: np.ndarray, top: np.ndarray) -> np.ndarray:
    """Closed solid from a bottom and a top quad, each (4, 3) CCW seen from above -> (12, 3, 3) outward."""
    c = np.concatenate([bottom, top])
    return c[_HEX_FACES]


def box(lo, hi) -> np.ndarray:
    """Axis-aligned box [lo, hi] (each (3,)) -> triangles (12, 3, 3) outward."""
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    q = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    return hexahedron(np.column_stack([q, np.full(4, z0)]), np.column_stack([q, np.full(4, z1)]))


def icosphere() -> np.ndarray:
    """Unit sphere: an icosahedron with each face split in four, projected -> triangles (80, 3, 3) outward."""
    g = (1 + 5 ** 0.5) / 2
    v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                  [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], float)
    f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4],
                  [11, 10, 2], [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8],
                  [3, 8, 9], [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    ab, bc, ca = (a + b) / 2, (b + c) / 2, (c + a) / 2
    t = np.concatenate([np.stack(x, 1) for x in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return t / np.linalg.norm(t, axis=2, keepdims=True)


def _car(L, W, H) -> np.ndarray:
    """Car along x centred at the origin, wheels on z = 0: body, tapered cabin, four wheels."""
    body = box((-L / 2, -W / 2, 0.3), (L / 2, W / 2, 0.55 * H + 0.1))
    zb = 0.55 * H + 0.1
    def q(x0, x1, y, z):
        return np.array([[x0, -y, z], [x1, -y, z], [x1, y, z], [x0, y, z]])

    cab = hexahedron(q(-0.32 * L, 0.22 * L, W / 2 - 0.05, zb), q(-0.22 * L, 0.08 * L, W / 2 - 0.2, H))
    wheels = [box((sx * L * 0.32 - 0.3, sy * (W / 2 - 0.12) - 0.12, 0.0), (sx * L * 0.32 + 0.3,
                                                                          sy * (W / 2 - 0.12) + 0.12, 0.6))
              for sx in (-1, 1) for sy in (-1, 1)]
    return np.concatenate([body, cab, *wheels])


def _tree(rng, p: OccluderParams):
    """A tree at the origin: (trunk (16, 3, 3), crown (80, 3, 3)) triangles; 4-10 m tall."""
    h = rng.uniform(*p.tree_height_m)
    R = min(rng.uniform(*p.crown_radius_m), 0.35 * h)
    zb = max(2.2, h - 2.6 * R)
    tr = rng.uniform(0.1, 0.2)
    ang = np.linspace(0, 2 * np.pi, 9)[:-1]
    ring = np.column_stack([tr * np.cos(ang), tr * np.sin(ang)])
    a, b = np.arange(8), (np.arange(8) + 1) % 8
    lo, hi = np.column_stack([ring, np.zeros(8)]), np.column_stack([ring, np.full(8, zb + 0.5)])
    trunk = np.concatenate([np.stack([lo[a], lo[b], hi[b]], 1), np.stack([lo[a], hi[b], hi[a]], 1)])
    crown = icosphere() * [R, R, 0.5 * (h - zb)] + [0, 0, 0.5 * (h + zb)]
    crown = crown + rng.normal(0, 0.04 * R, crown.shape)  # per corner: a lumpy, slightly open crown
    return trunk, crown


def _place(tris: np.ndarray, street, lateral: float, along: float) -> np.ndarray:
    """Move an object built along x at the origin to a street side: street = (axis, centre, side);
    ``lateral`` metres from the road centre line, ``along`` the road; turned to run with the road."""
    ax, c, side = street
    p = np.array(tris, float)
    if ax == 0:  # road runs along y: turn local x (length) onto world y
        p = np.stack([-p[..., 1], p[..., 0], p[..., 2]], axis=-1)
    xy = np.zeros(2)
    xy[ax], xy[1 - ax] = c + side * lateral, along
    return p + [xy[0], xy[1], 0.0]


def _bounds(p: np.ndarray):
    return p.reshape(-1, 3).min(axis=0), p.reshape(-1, 3).max(axis=0)


def _free(boxes_lo, boxes_hi, obstacles) -> bool:
    if not obstacles:
        return True
    o = np.array(obstacles)
    for lo, hi in zip(boxes_lo, boxes_hi):
        if np.any(np.all((lo < o[:, 3:]) & (o[:, :3] < hi), axis=1)):
            return False
    return True


def building_obstacles(scene: Scene) -> list[list[float]]:
    """Keep-out boxes [xmin, ymin, zmin, xmax, ymax, zmax] of every building: its walls up to the roof
    top, and its outermost parts (eaves, balconies, ledges) above the height where they begin."""
    out = []
    for d in scene.meta["buildings"]:
        x0, y0, x1, y1 = d["bbox"]
        top = d["top_z_m"] + 1.0
        out.append([x0 - 0.15, y0 - 0.15, -1.0, x1 + 0.15, y1 + 0.15, top])
        m = max(d["protrusion_m"], d["overhang_m"]) + 0.15
        z_low = d["eave_z_m"] - 0.1
        if d["protrusion_m"] > 0:
            z_low = min(z_low, d["storey_height_m"] - 0.3)
        out.append([x0 - m, y0 - m, z_low, x1 + m, y1 + m, top])
    return out


def make_occluders(rng: np.random.Generator, scene: Scene, density: float = 1.0,
                   params: OccluderParams = OccluderParams(), first_id: int = 0) -> Occluders:
    """Trees and pedestrians on the sidewalks, cars parked along the road edges, fences before facades.

    scene: a scene whose truth and ``meta['buildings']`` / ``meta['roads']`` are filled (its
    occluders are ignored). density: multiplies every rate. Instance ids start at ``first_id``.
    Side effect: writes ``scene.meta['cars']`` = [{"id", "centre": [x, y, z], "size": [length,
    width, height], "axis": 0 | 1 (length along x | y)}] and ``scene.meta['occluders']`` =
    [{"id", "class": OccluderClass name, "bbox": [xmin, ymin, zmin, xmax, ymax, zmax]}].
    Returns Occluders whose mesh has face_class = OccluderClass and face_building = instance id.
    """
    ext = scene.extent
    obstacles = building_obstacles(scene)
    roads = [tuple(r) for r in scene.meta.get("roads", [])]
    parts, cars, records = [], [], []

    def add(cls, tris_list, colors, boxes, extra=None):
        lo = np.array([b[0] for b in boxes])
        hi = np.array([b[1] for b in boxes])
        if lo[:, 0].min() < ext[0] or lo[:, 1].min() < ext[1] or hi[:, 0].max() > ext[2] or hi[:, 1].max() > ext[3]:
            return False
        if not _free(lo, hi, obstacles):
            return False
        oid = first_id + len(records)
        for tris, rgb in zip(tris_list, colors):
            parts.append((tris, cls, oid, rgb))
        for a, b in zip(lo, hi):
            obstacles.append([*a, *b])
        records.append({"id": oid, "class": OccluderClass(cls).name,
                        "bbox": [*map(float, lo.min(0)), *map(float, hi.max(0))]})
        if extra is not None:
            cars.append({"id": oid, **extra})
        return True

    for ax, c, hw in roads:
        b = 1 - ax
        length = ext[b + 2] - ext[b]
        crossings = [(c2, hw2) for a2, c2, hw2 in roads if a2 != ax]
        for side in (-1.0, 1.0):
            def spots(rate, b=b, length=length, crossings=crossings):
                k = rng.poisson(rate * density * length / 100.0)
                return [s for s in np.sort(rng.uniform(ext[b], ext[b + 2], k))
                        if all(abs(s - c2) >= hw2 + params.crossing_clear_m for c2, hw2 in crossings)]

            street = (ax, c, side)
            for s in spots(params.trees_per_100m):
                trunk, crown = _tree(rng, params)
                lat = hw + rng.uniform(*params.tree_from_curb_m)
                trunk, crown = _place(trunk, street, lat, s), _place(crown, street, lat, s)
                green = np.clip([60, 110, 50] + rng.integers(-20, 20, 3), 0, 255)
                add(OccluderClass.TREE, [trunk, crown], [(95, 75, 55), green], [_bounds(trunk), _bounds(crown)])
            for s in spots(params.cars_per_100m):
                L, W, H = (rng.uniform(*params.car_length_m), rng.uniform(*params.car_width_m),
                           rng.uniform(*params.car_height_m))
                tris = _place(_car(L, W, H), street, hw - rng.uniform(*params.car_centre_from_curb_m), s)
                lo, hi = _bounds(tris)
                add(OccluderClass.CAR, [tris], [rng.integers(30, 230, 3)], [(lo - [0.4, 0.4, 0], hi + [0.4, 0.4, 0])],
                    {"centre": [*map(float, 0.5 * (lo[:2] + hi[:2])), float(0.5 * hi[2])],
                     "size": [float(L), float(W), float(H)], "axis": int(b)})
            for s in spots(params.pedestrians_per_100m):
                h = rng.uniform(1.6, 1.85)
                body = hexahedron(np.array([[-0.22, -0.15, 0], [0.22, -0.15, 0], [0.22, 0.15, 0], [-0.22, 0.15, 0]]),
                                  np.array([[-0.25, -0.17, h - 0.25], [0.25, -0.17, h - 0.25], [0.25, 0.17, h - 0.25],
                                            [-0.25, 0.17, h - 0.25]]))
                tris = _place(np.concatenate([body, box((-0.1, -0.1, h - 0.25), (0.1, 0.1, h))]), street,
                              hw + rng.uniform(*params.pedestrian_from_curb_m), s)
                add(OccluderClass.PEDESTRIAN, [tris], [rng.integers(20, 220, 3)], [_bounds(tris)])
    _fences(rng, scene, params, add)
    if parts:
        tris = np.concatenate([p[0] for p in parts])
        mesh = Mesh(vertices=tris.reshape(-1, 3), faces=np.arange(3 * len(tris)).reshape(-1, 3),
                    face_class=np.concatenate([np.full(len(p[0]), p[1], np.uint8) for p in parts]),
                    face_building=np.concatenate([np.full(len(p[0]), p[2], np.int32) for p in parts]),
                    face_color=np.concatenate([np.tile(np.asarray(p[3], np.uint8), (len(p[0]), 1)) for p in parts]))
    else:
        mesh = Mesh.empty()
    scene.meta["cars"] = cars
    scene.meta["occluders"] = records
    return Occluders(mesh)


def _fences(rng, scene, params: OccluderParams, add):
    """A fence of panels parallel to part of the front facade, ``fence_from_facade_m`` in front of it."""
    for d in scene.meta["buildings"]:
        f = d["front_normal"]
        if f is None or rng.random() >= params.fence_p:
            continue
        x0, y0, x1, y1 = d["bbox"]
        ax = 0 if f[0] != 0 else 1  # the fence's offset axis
        b = 1 - ax
        lo_b, hi_b = (y0, y1) if ax == 0 else (x0, x1)
        span = hi_b - lo_b
        ua = lo_b + rng.uniform(0.0, 0.4) * span
        ub = ua + rng.uniform(0.3, 0.6) * span
        face = (x0 if f[0] < 0 else x1) if ax == 0 else (y0 if f[1] < 0 else y1)
        off = face + np.sign(f[ax]) * rng.uniform(*params.fence_from_facade_m)
        h = rng.uniform(*params.fence_height_m)
        edges = np.arange(ua, ub, 2.5)
        panels, boxes = [], []
        for e in edges:
            lo, hi = np.zeros(3), np.zeros(3)
            lo[ax], hi[ax] = off - 0.025, off + 0.025
            lo[b], hi[b] = e, min(e + 2.35, ub)
            lo[2], hi[2] = 0.0, h
            panels.append(box(lo, hi))
            boxes.append((lo, hi))
        if panels:
            add(OccluderClass.FENCE, [np.concatenate(panels)], [(150, 150, 145)], boxes)
