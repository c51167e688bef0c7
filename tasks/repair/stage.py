"""The repair stage on the work dir: repair one region of the plan (fuse -> mesh -> stitch -> texture) and
write ``regions/{key}/`` (:mod:`storage.contracts.region_mesh`).

:func:`run_region` (unit: a region) returns a small dict and never raises for a bad input (see
``tasks.units.run_unit``); it is redone when its plan entry, its tiles' stores, the cameras file or the
parameters change (:func:`region_fingerprint`).
"""

from __future__ import annotations

import json
import time

import numpy as np

from storage.atomic import file_fingerprint
from storage.contracts.region_mesh import (
    ATLAS_FILE,
    REGION_FILE,
    clear_region,
    write_region_doc,
    write_region_mesh,
)
from storage.contracts.region_plan import (
    REGION_SCHEMA_VERSION,
    REGIONS_DIR,
    Region,
    occupancy_path,
    read_plan,
    region_dir,
)
from storage.formats.camera_files import camera_files
from storage.ids import TileId
from storage.patches.schema import PATCHES_FILE
from storage.patches.state import store_fingerprint
from storage.workdir.layout import WorkDir, campus_frame, read_campus
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.repair.region_io import RegionRead, read_region
from tasks.repair.texture_inputs import camera_paths, image_loader, load_cameras, occupancy, reduced_texture
from tasks.units import Done, pending_units, run_unit


def _occupied_voxels(cfg: CampusConfig, wd: WorkDir, origin: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                     box: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(k, 3) float64 MLS-occupied voxel centres inside ``box`` from the tiles within
    ``occluder_radius_m`` of the region's bounds [lo, hi] (campus-local; origin: (3,) float64 world)."""
    tc = cfg.repair.texture
    vox = []
    for ix, iy in cfg.grid().tiles_for_bounds(lo + origin, hi + origin, tc.occluder_radius_m).tolist():
        t = TileId(ix, iy)
        if (wd.tile_dir(t) / PATCHES_FILE).exists():
            c = occupancy(wd.tile_dir(t), occupancy_path(wd.root, t.key), tc.occluder_voxel_m)
            vox.append(c[np.all((c >= box[0]) & (c <= box[1]), axis=1)])
    return np.concatenate(vox).astype(np.float64) if vox else np.zeros((0, 3))


def _texture_region(mesh, rr: RegionRead, cfg: CampusConfig, wd: WorkDir, frame, cams_all: list
                    ) -> tuple[object, np.ndarray, dict]:
    """Atlas + per-face colours of a rebuilt mesh. Returns (atlas or None, (m, 3) uint8 colours, stats)."""
    from tasks.repair.region_texture import (
        cameras_near,
        fallback_colors,
        occluder_box,
        texture_region,
        voxels_between,
    )

    textures = rr.textures
    colors = fallback_colors(mesh, rr.input, rr.zone_attrs["uv"], rr.zone_attrs["texture"],
                             lambda i: reduced_texture(textures[i]) if i < len(textures) else None)
    tc = cfg.repair.texture
    if not tc.enabled or not cams_all:
        return None, colors, {"cameras": 0}
    lo, hi = mesh.xyz.min(0), mesh.xyz.max(0)
    cams = cameras_near(cams_all, lo, hi, tc.max_distance_m)
    box = occluder_box(lo, hi, cams, tc.occluder_radius_m)
    vox = _occupied_voxels(cfg, wd, frame.origin_array, lo, hi, box)
    vox = vox[voxels_between(vox, lo, hi, cams, tc.occluder_voxel_m)]
    return texture_region(mesh, rr.input, cams, vox, tc, colors, image_loader(cams))


def camera_fingerprint(cfg: CampusConfig) -> str | None:
    """Fingerprint of the camera files the texture step reads (a COLMAP model: images.txt and
    cameras.txt, the intrinsics and distortion), or None without texturing or cameras."""
    _, cams = camera_paths(cfg)
    if not cfg.repair.texture.enabled or cams is None or not cams.exists():
        return None
    return combine_fingerprints([f"{f.name}:{file_fingerprint(f)}" for f in camera_files(cams) if f.is_file()])


def region_fingerprint(region: Region, wd: WorkDir, cfg: CampusConfig, memo: dict | None = None) -> str:
    """What a region's output depends on besides the parameters: its patch sets and grades (the plan
    entry), the stores of its tiles, and the cameras file. ``memo``: a dict shared by the regions of one
    plan so each tile store and the cameras file is fingerprinted once (:func:`pending_regions`)."""
    memo = {} if memo is None else memo
    parts = [json.dumps(region.to_json(), sort_keys=True)]
    for t in region.tiles:
        if t not in memo:
            memo[t] = store_fingerprint(wd.tile_dir(TileId.from_key(t)))
        parts.append(f"{t}:{memo[t]}")
    if ("cameras",) not in memo:
        memo[("cameras",)] = camera_fingerprint(cfg)
    if memo[("cameras",)] is not None:
        parts.append(memo[("cameras",)])
    return combine_fingerprints(parts)


def region_params(cfg: CampusConfig) -> dict:
    """The parameters a region's record is keyed by: ``repair.*``, the grid, and the MLS strips held out of
    the repair (``quality.holdout_*``; none when the share is 0)."""
    holdout = cfg.quality.holdout()
    return {"repair": cfg.repair.params(), "grid": cfg.grid().to_json(),
            **({"holdout": holdout.to_json()} if holdout.enabled else {})}


def pending_regions(region_keys: list[str], cfg: CampusConfig, wd: WorkDir) -> tuple[list[str], list[dict]]:
    """The regions of ``region_keys`` that must be repaired, from one read of the plan and of the region
    records (``tasks.units.pending_units``): (keys to run, in the given order; summaries of the skipped).
    A key the plan does not name is kept to run, so :func:`run_region` reports it."""
    plan = {r.key: r for r in read_plan(wd.root)}
    memo: dict = {}
    fps = {k: region_fingerprint(plan[k], wd, cfg, memo) for k in region_keys if k in plan}
    run, skipped = pending_units(wd, "region", fps, region_params(cfg))
    todo = set(run)
    return [k for k in region_keys if k in todo or k not in plan], skipped


def _write_rebuilt(out_dir, geo, rr: RegionRead, colors: np.ndarray, atlas, cfg: CampusConfig, origin) -> list[str]:
    """Write a rebuilt region's mesh, fused points and atlas; returns the file names written."""
    mesh = geo.mesh
    rep = np.flatnonzero(geo.replaced)
    arrays = {"vertices": mesh.xyz, "vertex_id": mesh.vertex_id, "vertex_source": mesh.source, "faces": mesh.faces,
              "face_patch": cfg.grid().keys_local(mesh.xyz[mesh.faces].mean(axis=1), origin),
              "uv": atlas.uv if atlas is not None else np.full((mesh.n_faces, 3, 2), np.nan, np.float32),
              "face_color": colors, "replaced_tile": rr.zone_tile[rep], "replaced_row": rr.zone_row[rep]}
    image = atlas.image if atlas is not None else None
    return write_region_mesh(out_dir, arrays, geo.fused_xyz, geo.fused_source, image)


def _summary(region: Region, rr: RegionRead, geo, status: str, t: tuple[float, float, float]) -> dict:
    """The unit summary of a repaired region (t: start, geometry done, texture done). The unit's peak RSS
    is added by :func:`tasks.units.run_unit`; tracing allocations (tracemalloc) made the geometry ~1.6x
    slower, so it is not done here."""
    t0, t1, t2 = t
    return {"region": region.key, "number": region.number, "result": status,
            "defect_type": geo.evidence.type, "n_patches": region.n_patches, "n_bad": len(region.bad),
            "tiles": list(region.tiles), "zone_faces": len(rr.input.zone_faces),
            "replaced_faces": int(geo.replaced.sum()), "rebuilt_faces": geo.mesh.n_faces,
            "max_border_gap_m": geo.stats.get("border", {}).get("max_gap_m", 0.0),
            "kept_agreeing_faces": geo.stats.get("agreeing", {}).get("kept_faces", 0),
            "unsupported_faces_dropped": geo.stats.get("unsupported_faces_dropped", 0),
            "input_faces_restored": geo.stats.get("input_faces_restored", 0),
            "step_seconds": {"read": rr.seconds, **geo.stats.get("seconds", {}), "texture": t2 - t1, "total": t2 - t0}}


def run_region(region_id: str, cfg: CampusConfig, wd: WorkDir, plan: dict[str, Region] | None = None) -> dict:
    """Repair one region (fuse -> mesh -> stitch -> texture) and write ``regions/{region_id}/``.

    Skipped when its manifest record is done with the same fingerprint (:func:`region_fingerprint`)
    and parameters (:func:`region_params`). ``plan``: {key: Region} of ``regions/regions.json`` when the
    caller read it once for a batch (else it is read here). Returns the unit summary: status, defect
    type, counts, border gap, seconds per step (and the peak RSS, from ``run_unit``).
    """
    plan = {r.key: r for r in read_plan(wd.root)} if plan is None else plan
    if region_id not in plan:
        return {"unit": region_id, "status": "failed", "error": f"region {region_id} is not in the plan "
                "(regions/regions.json): run the regions stage first", "skipped": False}
    region = plan[region_id]
    params = region_params(cfg)
    out_dir = region_dir(wd.root, region_id)

    def work() -> Done:
        from tasks.repair.region_geometry import repair_region_geometry

        t0 = time.perf_counter()
        doc = read_campus(wd)
        frame = campus_frame(doc)
        rr = read_region(region, cfg.grid(), wd.tile_dir, frame.origin, cfg.quality.holdout())
        geo = repair_region_geometry(rr.input, cfg.repair)
        t1 = time.perf_counter()
        clear_region(out_dir)
        tex_stats, status, written = {}, "kept", []
        if geo.mesh.n_faces:
            status = "rebuilt"
            cams = load_cameras(cfg, doc, frame) if cfg.repair.texture.enabled else []
            atlas, colors, tex_stats = _texture_region(geo.mesh, rr, cfg, wd, frame, cams)
            written = _write_rebuilt(out_dir, geo, rr, colors, atlas, cfg, frame.origin)
        t2 = time.perf_counter()
        summary = _jsonable(_summary(region, rr, geo, status, (t0, t1, t2)))
        write_region_doc(out_dir, {
            "schema_version": REGION_SCHEMA_VERSION, "key": region_id, "number": region.number, "status": status,
            "patches": region.patches.tolist(), "bad": region.bad.tolist(), "tiles": list(region.tiles),
            "parent": region.parent, "replaced_tiles": rr.tiles, "evidence": geo.evidence.to_json(),
            "stats": _jsonable(geo.stats), "texture": _jsonable(tex_stats),
            "atlas": ATLAS_FILE if ATLAS_FILE in written else None, "summary": summary})
        return Done(outputs=[f"{REGIONS_DIR}/{region_id}/{n}" for n in [*written, REGION_FILE]], summary=summary)

    return run_unit(wd, "region", region_id, region_fingerprint(region, wd, cfg), params, work)


def _jsonable(x):
    """``x`` with numpy scalars and arrays as Python values and non-finite floats as None (for JSON)."""
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    return x
