"""Synthetic terrain: GROUND and ROAD quads on a grid cut at road edges and building outlines, none under
buildings but in their through-passages. Mesh frame, metres, float64, terrain at z = 0 (roads at
``road_z_m``)."""

from __future__ import annotations

import numpy as np

from .scene import CLASS_COLOR, FaceClass, Mesh, soup_to_mesh


def terrain_cells(extent, roads, infos: list[dict]):
    """The terrain grid: cell bounds xs (nx + 1,), ys (ny + 1,) cut at road edges and building bbox /
    notch / passage lines; road (nx, ny) bool: cell on a road; inside (nx, ny) bool: cell under a
    building (a through-passage's floor is not: the ground runs through)."""
    x0, y0, x1, y1 = extent
    br = [r for inf in infos for r in [inf["bbox"]] + ([inf["cut"]] if inf["cut"] is not None else [])
          + ([inf["passage"]["rect"]] if inf.get("passage") else [])]
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
        if inf.get("passage"):  # the ground runs through a passage
            q = inf["passage"]["rect"]
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
