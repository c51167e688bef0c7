"""Synthetic campus truth: a road grid, terrain and buildings with windows, doors, balconies and eaves.

:func:`make_scene` draws the building records (footprint, storeys, roof, facade style) and assembles
the scene from :mod:`synth.layout` (roads, footprints), :mod:`synth.facades` (one building's mesh),
:mod:`synth.terrain` and :mod:`synth.occluders`.

Frames and units: mesh frame, metres, float64, z up, terrain at z = 0 (roads at ``road_z_m``).
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from .envelope import Chart, building_charts, l_polygon
from .facades import FacadeParams, building_mesh, jitter_colour
from .layout import LayoutParams, place_footprints, road_lines
from .scene import CLASS_COLOR, Building, FaceClass, Mesh, Occluders, Scene
from .terrain import terrain_mesh

DEFAULT_LAYOUT, DEFAULT_FACADE = LayoutParams(), FacadeParams()  # frozen: shared safely as defaults


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
               storeys: tuple[int, int] = (1, 12), layout: LayoutParams = DEFAULT_LAYOUT,
               facade: FacadeParams = DEFAULT_FACADE, occluder_density: float = 1.0,
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
    placed = place_footprints(rng, extent, n_buildings, roads, layout, [max(p[1], p[2]) + 0.05 for p in plan])
    buildings, infos, meshes = [], [], []
    for k, (bbox, front, _) in enumerate(placed):
        style, prot, overhang = plan[k]
        b, info = _building_record(rng, first_building_id + k, bbox, front, storeys, layout, facade, style, prot,
                                   overhang)
        wall_rgb = jitter_colour(rng, CLASS_COLOR[FaceClass.WALL], 40)
        roof_rgb = jitter_colour(rng, CLASS_COLOR[FaceClass.ROOF], 25)
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
