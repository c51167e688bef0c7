"""The repair stages on the work dir: plan the regions, then repair each region.

Stage functions (called by ``flows/campus.py``; they return small dicts and never raise for a bad
input, see ``tasks.units.run_unit``):

- :func:`run_regions` (unit: the campus) -> plan summary with ``regions``: the region keys to map;
- :func:`run_region` (unit: a region) -> summary; redone when its patches, their tiles' stores, its
  grades, the cameras file or the parameters change (:func:`region_fingerprint`);
- :func:`tasks.repair.texture_inputs.run_occupancy_tile` (unit: a tile, optional ahead of the regions);
- :func:`tasks.repair.region_io.region_meshes_for_tile` -> what a tile's merge needs (re-exported here).

The on-disk format of a region is documented in :mod:`tasks.repair.region_io`.
"""

from __future__ import annotations

import json
import shutil
import time
import tracemalloc

import numpy as np

from storage.atomic import file_fingerprint, write_json_atomic
from storage.ids import TileId
from storage.manifest import ManifestRecord, combine_fingerprints, write_record
from storage.patch_store import PATCHES_FILE, PatchStore
from storage.workdir import WorkDir, campus_frame, read_campus
from tasks.config import CampusConfig
from tasks.repair.region_io import (  # noqa: F401 - RegionMesh and region_meshes_for_tile are re-exported for the merge
    REGION_SCHEMA_VERSION,
    RegionMesh,
    RegionRead,
    read_region,
    region_dir,
    region_meshes_for_tile,
    tile_fingerprint,
    write_region_mesh,
)
from tasks.regions.plan import (
    REGIONS_DIR,
    Region,
    patch_cost_bytes,
    patch_grades,
    plan_path,
    plan_regions,
    read_plan,
)
from tasks.repair.texture_inputs import camera_paths, load_cameras, occupancy, reduced_texture, run_occupancy_tile  # noqa: F401
from tasks.units import STAGE_VERSIONS, Done, run_unit



# ----------------------------------------------------------------------------------------- plan

def run_regions(cfg: CampusConfig, wd: WorkDir) -> dict:
    """Plan the regions over every live tile and write ``regions/regions.json``.

    Reads each tile's patches table and grades (:func:`tasks.regions.plan.patch_grades` with
    ``cfg.repair.grades``); removes the folders of regions the plan no longer names. Returns
    {"regions": [keys], "n_bad", "n_regions", "split", "grades": {tile: source}, "seconds"}.
    """
    t0 = time.perf_counter()
    rc = cfg.repair.regions
    grid = cfg.grid()
    keys, bad, cost, sources, tile_fp = [], [], [], {}, {}
    for t in wd.live_tiles():
        store = PatchStore(wd.tile_dir(t))
        k, g, src = patch_grades(store, cfg.repair.grades)
        p = store.patches()
        keys.append(k)
        bad.append(k[g == 1])
        cost.append(patch_cost_bytes(p["n_points"], p["n_faces"]))
        sources[t.key] = src
        tile_fp[t.key] = tile_fingerprint(wd.tile_dir(t))
    all_keys = np.concatenate(keys) if keys else np.zeros(0, np.int64)
    order = np.argsort(all_keys)
    all_keys = all_keys[order]
    cost_all = np.concatenate(cost)[order] if cost else np.zeros(0)
    bad_keys = np.concatenate(bad) if bad else np.zeros(0, np.int64)
    regions = plan_regions(bad_keys, all_keys, grid, min_patches=rc.min_patches, grow_cells=rc.grow_cells,
                           context_cells=rc.context_cells, patch_cost=cost_all,
                           budget_bytes=rc.memory_budget_mb * 2**20) if cfg.repair.enabled else []
    doc = {"schema_version": REGION_SCHEMA_VERSION, "grades": sources, "tile_fingerprints": tile_fp,
           "grid": grid.to_json(), "regions": [r.to_json() for r in regions]}
    write_json_atomic(plan_path(wd.root), doc, indent=None)
    names = {r.key for r in regions}
    root = wd.root / REGIONS_DIR
    removed = 0
    for d in root.iterdir() if root.exists() else []:
        if d.is_dir() and d.name not in names and not d.name.startswith("_"):
            shutil.rmtree(d, ignore_errors=True)
            (wd.manifest_dir / "region" / f"{d.name}.json").unlink(missing_ok=True)
            removed += 1
    out = {"regions": sorted(names), "n_regions": len(regions), "n_bad": len(bad_keys),
           "n_patches_rebuilt": int(sum(r.n_patches for r in regions)),
           "split": int(sum(bool(r.parent) for r in regions)), "removed": removed,
           "grades": sorted(set(sources.values())), "seconds": time.perf_counter() - t0}
    write_record(wd, ManifestRecord("regions", "campus", "done", seconds=out["seconds"],
                                    summary={k: v for k, v in out.items() if k != "regions"}))
    return out


# ----------------------------------------------------------------------------------------- one region

def _texture_region(mesh, rr: RegionRead, region: Region, cfg: CampusConfig, wd: WorkDir, doc, frame,
                    cams_all) -> tuple[object, np.ndarray, dict]:
    """Atlas + per-face colours of a rebuilt mesh. Returns (atlas or None, (m, 3) uint8 colours, stats)."""
    from tasks.repair.mesh import ClosestPoint
    from tasks.repair.texture import sample_texture_colors, texture_mesh, voxel_boxes

    d = rr.input
    faces = mesh.faces
    tri = mesh.xyz[faces]
    cen = tri.mean(axis=1)
    # fallback colour: the original texture at the closest replaced face
    fid, bary, _ = ClosestPoint(d.xyz, d.zone_faces).query(cen)
    fid = np.maximum(fid, 0)
    uv = np.einsum("kc,kcd->kd", bary, rr.zone_attrs["uv"][fid].astype(np.float64))
    texpaths = rr.textures
    colors = sample_texture_colors(uv, rr.zone_attrs["texture"][fid],
                                   lambda i: reduced_texture(texpaths[i]) if i < len(texpaths) else None)
    tc = cfg.repair.texture
    if not tc.enabled or not cams_all:
        return None, colors, {"cameras": 0}
    lo, hi = mesh.xyz.min(0), mesh.xyz.max(0)
    centres = np.stack([c.centre for c in cams_all])
    gap = np.maximum(np.maximum(lo - centres, centres - hi), 0)
    near = np.flatnonzero(np.linalg.norm(gap, axis=1) <= tc.max_distance_m)
    cams = [cams_all[i] for i in near]
    # occluders: retained faces around the region + MLS-occupied voxels off the rebuilt surface
    grid = cfg.grid()
    r = tc.occluder_radius_m
    vox = []
    # only what lies between the region and its cameras can hide it
    cc = np.stack([c.centre for c in cams]) if cams else np.zeros((0, 3))
    box_lo = np.maximum(np.minimum(lo, cc.min(0)) if len(cc) else lo, lo - r)
    box_hi = np.minimum(np.maximum(hi, cc.max(0)) if len(cc) else hi, hi + r)
    for ix, iy in grid.tiles_for_bounds(lo + frame.origin_array, hi + frame.origin_array, r).tolist():
        t = TileId(ix, iy)
        if (wd.tile_dir(t) / PATCHES_FILE).exists():
            c = occupancy(wd, t, tc.occluder_voxel_m)
            sel = np.all((c >= box_lo) & (c <= box_hi), axis=1)
            vox.append(c[sel])
    vox = np.concatenate(vox).astype(np.float64) if vox else np.zeros((0, 3))
    surf_v = np.concatenate([mesh.xyz, d.xyz])
    surf_f = np.concatenate([faces, d.context_faces + len(mesh.xyz)])
    if len(vox):
        dist = ClosestPoint(surf_v, surf_f).query(vox)[2]
        vox = vox[dist > 0.3 + 0.87 * tc.occluder_voxel_m]
    bv, bf = voxel_boxes(vox, tc.occluder_voxel_m)
    occ_v = np.concatenate([d.xyz, bv])
    occ_f = np.concatenate([d.context_faces, bf + len(d.xyz)])
    images: dict[int, np.ndarray] = {}

    def load_image(i):
        if i not in images:
            from PIL import Image

            images[i] = np.asarray(Image.open(cams[i].image).convert("RGB"))
        return images[i]

    atlas, st = texture_mesh(mesh.xyz, faces, cams, load_image, (occ_v, occ_f), tc, colors)
    st["occluder_voxels"] = len(vox)
    if atlas.image is not None:  # textured faces take the mean image colour as their fallback colour
        for lab in np.unique(atlas.view[atlas.view >= 0]):
            sel = atlas.view == lab
            px, _ = cams[int(lab)].project(cen[sel])
            img = load_image(int(lab))
            x = np.clip(np.round(px[:, 0]).astype(int), 0, img.shape[1] - 1)
            y = np.clip(np.round(px[:, 1]).astype(int), 0, img.shape[0] - 1)
            colors[sel] = img[y, x]
    return atlas, colors, st


def region_fingerprint(region: Region, wd: WorkDir, cfg: CampusConfig) -> str:
    """What a region's output depends on besides the parameters: its patch sets and grades (the plan
    entry), the stores of its tiles, and the cameras file."""
    parts = [json.dumps(region.to_json(), sort_keys=True)]
    parts += [f"{t}:{tile_fingerprint(wd.root / 'tiles' / t)}" for t in region.tiles]
    _, cams = camera_paths(cfg)
    if cfg.repair.texture.enabled and cams is not None and cams.exists():
        parts.append(file_fingerprint(cams))
    return combine_fingerprints(parts)


def run_region(region_id: str, cfg: CampusConfig, wd: WorkDir) -> dict:
    """Repair one region (fuse -> mesh -> stitch -> texture) and write ``regions/{region_id}/``.

    Skipped when its manifest record is done with the same fingerprint (:func:`region_fingerprint`)
    and parameters (``cfg.repair.params()`` + the grid). Returns the unit summary: status, defect
    type, counts, border gap, seconds per step, peak traced memory.
    """
    plan = {r.key: r for r in read_plan(wd.root)}
    if region_id not in plan:
        return {"unit": region_id, "status": "failed", "error": f"region {region_id} is not in the plan "
                "(regions/regions.json): run the regions stage first", "skipped": False}
    region = plan[region_id]
    params = {"repair": cfg.repair.params(), "grid": cfg.grid().to_json()}
    fp = region_fingerprint(region, wd, cfg)
    out_dir = region_dir(wd, region_id)

    def work() -> Done:
        from tasks.repair.geometry import repair_region_geometry

        tracemalloc.start()
        t0 = time.perf_counter()
        doc = read_campus(wd)
        frame = campus_frame(doc)
        rr = read_region(region, cfg, wd, frame)
        geo = repair_region_geometry(rr.input, cfg.repair)
        t1 = time.perf_counter()
        (out_dir / "region.json").unlink(missing_ok=True)  # the 'done' marker goes first, comes back last
        for name in ("mesh.npz", "fused.npz", "atlas.jpg"):
            (out_dir / name).unlink(missing_ok=True)
        tex_stats, status = {}, "kept"
        outputs = []
        if geo.mesh.n_faces:
            status = "rebuilt"
            cams = load_cameras(cfg, doc, frame) if cfg.repair.texture.enabled else []
            atlas, colors, tex_stats = _texture_region(geo.mesh, rr, region, cfg, wd, doc, frame, cams)
            write_region_mesh(out_dir, geo, rr, colors, atlas, cfg, frame)
            outputs += [f"{REGIONS_DIR}/{region_id}/mesh.npz", f"{REGIONS_DIR}/{region_id}/fused.npz"]
            if atlas is not None and atlas.image is not None:
                outputs.append(f"{REGIONS_DIR}/{region_id}/atlas.jpg")
        t2 = time.perf_counter()
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        summary = {"region": region_id, "number": region.number, "result": status,
                   "defect_type": geo.evidence.type, "n_patches": region.n_patches, "n_bad": len(region.bad),
                   "tiles": list(region.tiles), "zone_faces": len(rr.input.zone_faces),
                   "replaced_faces": int(geo.replaced.sum()), "rebuilt_faces": geo.mesh.n_faces,
                   "max_border_gap_m": geo.stats.get("border", {}).get("max_gap_m", 0.0),
                   "step_seconds": {"read": rr.seconds, **geo.stats.get("seconds", {}), "texture": t2 - t1,
                               "total": t2 - t0},
                   "peak_traced_mb": peak / 2**20}
        doc_r = {"schema_version": REGION_SCHEMA_VERSION, "key": region_id, "number": region.number,
                 "status": status, "patches": region.patches.tolist(), "bad": region.bad.tolist(),
                 "tiles": list(region.tiles), "parent": region.parent, "replaced_tiles": rr.tiles,
                 "evidence": geo.evidence.to_json(), "stats": _jsonable(geo.stats), "texture": _jsonable(tex_stats),
                 "atlas": "atlas.jpg" if (out_dir / "atlas.jpg").exists() else None,
                 "summary": _jsonable(summary)}
        write_json_atomic(out_dir / "region.json", doc_r, indent=None)
        outputs.append(f"{REGIONS_DIR}/{region_id}/region.json")
        return Done(outputs=outputs, summary=_jsonable(summary))

    return run_unit(wd, "region", region_id, fp, params, work)


def _jsonable(x):
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


