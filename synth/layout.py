"""Synthetic campus layout: a road grid and building footprints placed in the blocks between roads.

Roads lie on a *global* grid (``LayoutParams.road_spacing_m``, offset and widths derived from the
road index only), so a campus generated tile by tile (``make_scene(..., extent=tile)``) has roads
that line up across tile borders; buildings are placed only where they fit entirely in the extent.

Frames and units: mesh frame, metres, float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


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


def place_footprints(rng, extent, n, roads, layout: LayoutParams, margins: list[float]):
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
