"""The repair stages on the work dir: plan the regions, repair one region, and read the results back.

::

    regions/regions.json              the plan: one entry per region (key, number, patches, bad,
                                      context, tiles, parent), the grades source, the plan fingerprint
    regions/{key}/mesh.npz            the rebuilt mesh (format below); absent when the region is
                                      left to the mesh
    regions/{key}/fused.npz           the fused points: xyz (k, 3) float32 campus-local, source (k,)
                                      int8 (0 mesh vertex, 1 MLS point)
    regions/{key}/atlas.jpg           the region's texture atlas (absent when no image sees it)
    regions/{key}/region.json         status, evidence (defect type), replaced faces, figures; written
                                      last: its presence marks a complete region

``mesh.npz`` (numpy, uncompressed)::

    vertices     (n, 3) float32  metres, campus-local
    vertex_id    (n,)   int64    >= 0: the original mesh vertex id (border vertices: welded to the
                                 retained mesh; interior: an original vertex kept in place);
                                 < 0: a new vertex, unique within the region (not campus-wide)
    faces        (m, 3) int32    counter-clockwise seen from outside (like the input mesh)
    face_patch   (m,)   int64    patch key of each face's centroid (same rule as the partition): the
                                 tile of a face is ``grid.tile_of_keys(face_patch)``
    uv           (m, 3, 2) float32 per-corner atlas coordinates, OBJ convention (origin bottom-left);
                                 NaN for a face without atlas texture
    face_color   (m, 3) uint8    colour of each face (the image colour, or the original mesh texture's
                                 colour where no image sees the face): the fallback of untextured faces
    replaced_tile  (r,) int16    index into region.json "replaced_tiles"
    replaced_row   (r,) int64    row in that tile's faces.parquet of each original face it replaces

Stage functions (called by ``flows/campus.py``; they never raise for a bad input, see
``tasks.units.run_unit``):

- :func:`run_regions` (unit: the campus) -> plan summary with ``regions``: the region keys to map;
- :func:`run_region` (unit: a region) -> summary; redone when its patches, their tiles' stores,
  its grades, the cameras or the parameters change;
- :func:`region_meshes_for_tile` -> the pieces of the rebuilt regions a tile's merge needs.
"""

from __future__ import annotations

import json
import shutil
import time
import tracemalloc
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path, file_fingerprint, write_json_atomic
from storage.errors import InputError
from storage.ids import TileId
from storage.manifest import ManifestRecord, combine_fingerprints, write_record
from storage.patch_store import PATCHES_FILE, PatchStore
from storage.workdir import WorkDir, campus_frame, read_campus
from tasks.config import CampusConfig
from tasks.regions import (
    BYTES_PER_FACE,
    BYTES_PER_POINT,
    REGIONS_DIR,
    Region,
    patch_grades,
    plan_path,
    plan_regions,
    read_plan,
)
from tasks.units import STAGE_VERSIONS, Done, run_unit

REGION_SCHEMA_VERSION = 1
STAGE_VERSIONS.setdefault("regions", 1)
STAGE_VERSIONS.setdefault("region", 1)

FACE_COLUMNS = [*(f"{a}{v}" for v in range(3) for a in "xyz"), "vid0", "vid1", "vid2", "nx", "ny", "nz",
                *(f"{a}{v}" for v in range(3) for a in "uv"), "texture", "red", "green", "blue"]
POINT_COLUMNS = ["x", "y", "z", "classification"]


def region_dir(wd: WorkDir, key: str) -> Path:
    return wd.root / REGIONS_DIR / key


# ----------------------------------------------------------------------------------------- plan

def _tile_fingerprint(tile_dir: Path) -> str:
    try:
        return file_fingerprint(tile_dir / PATCHES_FILE)
    except OSError:
        return "missing"


def run_regions(cfg: CampusConfig, wd: WorkDir) -> dict:
    """Plan the regions over every live tile and write ``regions/regions.json``.

    Reads each tile's patches table and grades (:func:`tasks.regions.patch_grades` with
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
        cost.append(p["n_points"].astype(np.float64) * BYTES_PER_POINT + p["n_faces"] * BYTES_PER_FACE)
        sources[t.key] = src
        tile_fp[t.key] = _tile_fingerprint(wd.tile_dir(t))
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
    out = {"regions": sorted(names), "n_regions": len(regions), "n_bad": int(len(bad_keys)),
           "n_patches_rebuilt": int(sum(r.n_patches for r in regions)),
           "split": int(sum(bool(r.parent) for r in regions)), "removed": removed,
           "grades": sorted(set(sources.values())), "seconds": time.perf_counter() - t0}
    write_record(wd, ManifestRecord("regions", "campus", "done", seconds=out["seconds"],
                                    summary={k: v for k, v in out.items() if k != "regions"}))
    return out


# ----------------------------------------------------------------------------------------- read

@dataclass
class RegionRead:
    """What :func:`read_region` returns: the pure input plus the references needed to write back."""

    input: object  # tasks.repair.RegionInput
    zone_tile: np.ndarray  # (mz,) int16 index into tiles
    zone_row: np.ndarray  # (mz,) int64 row in that tile's faces.parquet
    zone_attrs: dict  # uv (mz, 3, 2), texture (mz,) global texture index, rgb (mz, 3)
    tiles: list[str]
    textures: list[str]  # texture image paths (global index)
    seconds: float


def read_region(region: Region, cfg: CampusConfig, wd: WorkDir, frame) -> RegionRead:
    """Read the region's rebuilt and context patches from every tile they lie in (and nothing else)."""
    from tasks.repair import RegionInput
    from tasks.regions import dilate

    t0 = time.perf_counter()
    grid = cfg.grid()
    want = np.concatenate([region.patches, region.context])
    tiles = grid.tile_of_keys(want)
    zone_parts, ctx_parts, pts_zone, cls_zone, pts_ctx = [], [], [], [], []
    ztile, zrow, uv, tex, rgb = [], [], [], [], []
    textures: list[str] = []
    tile_keys = []
    zone_set = frozenset(region.patches.tolist())
    for ti, (ix, iy) in enumerate(np.unique(tiles, axis=0).tolist()):
        tile = TileId(ix, iy)
        store = PatchStore(wd.tile_dir(tile))
        tile_keys.append(tile.key)
        p = store.patches()
        sel = want[(tiles[:, 0] == ix) & (tiles[:, 1] == iy)]
        sel = sel[np.isin(sel, p["patch"])]
        tex_base = len(textures)
        textures += list(store.meta.textures)
        for pd in store.read_patches(sel.tolist(), POINT_COLUMNS, FACE_COLUMNS):
            f = pd.faces
            if pd.key not in zone_set:
                ctx_parts.append(f)
                pts_ctx.append(pd.xyz())
                continue
            zone_parts.append(f)
            pts_zone.append(pd.xyz())
            cls_zone.append(pd.points["classification"])
            if pd.n_faces:
                row = int(p["face_start"][np.searchsorted(p["patch"], pd.key)])
                ztile.append(np.full(pd.n_faces, ti, np.int16))
                zrow.append(np.arange(row, row + pd.n_faces, dtype=np.int64))
                uv.append(np.stack([np.stack([f[f"u{v}"], f[f"v{v}"]], 1) for v in range(3)], 1))
                tex.append(np.where(f["texture"] >= 0, f["texture"].astype(np.int64) + tex_base, -1))
                rgb.append(np.stack([f["red"], f["green"], f["blue"]], 1))
    zf = _concat_faces(zone_parts)
    cf = _concat_faces(ctx_parts)
    tri = np.concatenate([zf["tri"], cf["tri"]])
    vid = np.concatenate([zf["vid"], cf["vid"]])
    if (vid < 0).any():  # a store without vertex ids: weld exactly coincident corners instead
        _, cid = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
        vid = np.where(vid < 0, -2 - cid.reshape(vid.shape), vid)
    uid, first, inv = np.unique(vid.ravel(), return_index=True, return_inverse=True)
    xyz = tri.reshape(-1, 3)[first].astype(np.float64)
    faces = inv.reshape(-1, 3).astype(np.int64)
    mzn = len(zf["tri"])
    near = dilate(region.patches, 1)
    vkeys = grid.keys_local(xyz, frame.origin)
    cat = lambda xs, shape, dt: np.concatenate(xs) if xs else np.zeros(shape, dt)
    data = RegionInput(
        xyz=xyz, vertex_id=uid, zone_faces=faces[:mzn], context_faces=faces[mzn:],
        near_zone=np.isin(vkeys, near),
        mls_xyz=cat(pts_zone, (0, 3), np.float32).astype(np.float64), mls_class=cat(cls_zone, (0,), np.uint8),
        ctx_xyz=cat(pts_ctx, (0, 3), np.float32).astype(np.float64),
        face_normals=np.concatenate([zf["n"], cf["n"]]),
    )
    return RegionRead(data, cat(ztile, (0,), np.int16), cat(zrow, (0,), np.int64),
                      {"uv": cat(uv, (0, 3, 2), np.float32), "texture": cat(tex, (0,), np.int64),
                       "rgb": cat(rgb, (0, 3), np.uint8)}, tile_keys, textures, time.perf_counter() - t0)


def _concat_faces(parts: list[dict]) -> dict:
    if not parts or not sum(len(f["x0"]) for f in parts):
        return {"tri": np.zeros((0, 3, 3), np.float32), "vid": np.zeros((0, 3), np.int64),
                "n": np.zeros((0, 3), np.float32)}
    f = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    tri = np.stack([np.stack([f[f"{a}{v}"] for a in "xyz"], 1) for v in range(3)], 1)
    return {"tri": tri, "vid": np.stack([f[f"vid{v}"] for v in range(3)], 1),
            "n": np.stack([f["nx"], f["ny"], f["nz"]], 1)}


# ----------------------------------------------------------------------------------------- cameras, occupancy

OCCUPANCY_DIR = "_occupancy"


def camera_paths(cfg: CampusConfig) -> tuple[Path | None, Path | None]:
    """(images folder, cameras.json) from ``repair.texture`` (or ``inputs.images`` / ``inputs.cameras``
    when the config has them), else an ``images`` folder beside the first mesh input (synth layout)."""
    tc = cfg.repair.texture
    images = getattr(cfg.inputs, "images", None) or tc.images
    cams = getattr(cfg.inputs, "cameras", None) or tc.cameras
    if images is None and cfg.inputs.mesh:
        guess = Path(cfg.inputs.mesh[0]).parent / "images"
        images = str(guess) if (guess / "cameras.json").exists() else None
    if cams is None and images is not None:
        cams = str(Path(images) / "cameras.json")
    return (Path(images) if images else None), (Path(cams) if cams else None)


def load_cameras(cfg: CampusConfig, doc: dict, frame) -> list:
    """Every camera of cameras.json in the campus frame ([] when there are none).

    cameras.json: {"frame": "MLS" | "mesh", "frame_origin": [x, y, z] world, "cameras": [{"image", "K",
    "R", "t", "width", "height"}]} with X_cam = R (X_world - frame_origin) + t. MLS-frame poses go
    through the campus registration (campus.json), mesh-frame poses only through the origin shift.
    """
    from tasks.texture import cameras_to_frame

    images, path = camera_paths(cfg)
    if path is None or not path.exists():
        return []
    try:
        cj = json.loads(path.read_text())
        entries = cj["cameras"]
        fo = np.asarray(cj.get("frame_origin", [0.0, 0.0, 0.0]), np.float64)
    except (OSError, ValueError, KeyError) as e:
        raise InputError(path, f"not a cameras.json ({e})") from None
    oc = np.asarray(frame.origin, np.float64)
    m = np.eye(4)
    if str(cj.get("frame", "MLS")).lower() == "mls":
        reg = np.asarray(doc["registration"]["matrix"], np.float64)
        m[:3, :3] = reg[:3, :3]
        m[:3, 3] = reg[:3, :3] @ (fo - oc) + reg[:3, 3]
    else:
        m[:3, 3] = fo - oc
    return cameras_to_frame(entries, m, str(images or path.parent))


def occupancy(wd: WorkDir, tile: TileId, voxel_m: float) -> np.ndarray:
    """(k, 3) float32 centres of the tile's MLS-occupied voxels (campus-local), cached in
    ``regions/_occupancy/{tile}.npz`` and rebuilt when the tile's store changes."""
    tile_dir = wd.tile_dir(tile)
    fp = _tile_fingerprint(tile_dir)
    path = wd.root / REGIONS_DIR / OCCUPANCY_DIR / f"{tile.key}.npz"
    if path.exists():
        with np.load(path) as z:
            if str(z["fingerprint"]) == fp and float(z["voxel_m"]) == voxel_m:
                return z["centres"]
    store = PatchStore(tile_dir)
    pts, _ = store.read_all(point_columns=["x", "y", "z"], face_columns=["patch"])
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1)
    cells = np.unique(np.floor(xyz / voxel_m).astype(np.int64), axis=0)
    centres = ((cells + 0.5) * voxel_m).astype(np.float32)
    with atomic_path(path) as tmp:
        np.savez(tmp, centres=centres, fingerprint=np.array(fp), voxel_m=np.array(voxel_m))
    return centres


def run_occupancy_tile(tile: TileId, cfg: CampusConfig, wd: WorkDir) -> dict:
    """Build one tile's occupancy voxels ahead of the regions (optional: run_region builds missing ones)."""
    t0 = time.perf_counter()
    n = len(occupancy(wd, tile, cfg.repair.texture.occluder_voxel_m))
    return {"unit": tile.key, "status": "done", "voxels": n, "seconds": time.perf_counter() - t0}


_TEXTURE_CACHE: dict = {}


def _reduced_texture(path: str, max_side: int = 2048):
    """An original mesh texture decoded at reduced size (JPEG DCT scaling), cached per process."""
    from PIL import Image

    if path not in _TEXTURE_CACHE:
        try:
            im = Image.open(path)
            im.draft("RGB", (max_side, max_side))
            _TEXTURE_CACHE[path] = np.asarray(im.convert("RGB"))
        except OSError:
            _TEXTURE_CACHE[path] = None
        while len(_TEXTURE_CACHE) > 4:
            _TEXTURE_CACHE.pop(next(iter(_TEXTURE_CACHE)))
    return _TEXTURE_CACHE[path]


# ----------------------------------------------------------------------------------------- one region

def _texture_region(mesh, rr: RegionRead, region: Region, cfg: CampusConfig, wd: WorkDir, doc, frame,
                    cams_all) -> tuple[object, np.ndarray, dict]:
    """Atlas + per-face colours of a rebuilt mesh. Returns (atlas or None, (m, 3) uint8 colours, stats)."""
    from tasks.mesh import ClosestPoint
    from tasks.texture import sample_texture_colors, texture_mesh, voxel_boxes

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
                                   lambda i: _reduced_texture(texpaths[i]) if i < len(texpaths) else None)
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
    st["occluder_voxels"] = int(len(vox))
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
    parts += [f"{t}:{_tile_fingerprint(wd.root / 'tiles' / t)}" for t in region.tiles]
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
        from tasks.repair import repair_region_geometry

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
                   "defect_type": geo.evidence.type, "n_patches": region.n_patches, "n_bad": int(len(region.bad)),
                   "tiles": list(region.tiles), "zone_faces": int(len(rr.input.zone_faces)),
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


def write_region_mesh(out_dir: Path, geo, rr: RegionRead, colors: np.ndarray, atlas, cfg: CampusConfig, frame) -> None:
    """mesh.npz, fused.npz and atlas.jpg of a rebuilt region (format: module docstring)."""
    from PIL import Image

    mesh = geo.mesh
    cen = mesh.xyz[mesh.faces].mean(axis=1)
    face_patch = cfg.grid().keys_local(cen, frame.origin)
    uv = atlas.uv if atlas is not None else np.full((mesh.n_faces, 3, 2), np.nan, np.float32)
    rep = np.flatnonzero(geo.replaced)
    arrays = {"vertices": mesh.xyz.astype(np.float32), "vertex_id": mesh.vertex_id.astype(np.int64),
              "faces": mesh.faces.astype(np.int32), "face_patch": face_patch.astype(np.int64),
              "uv": uv.astype(np.float32), "face_color": colors.astype(np.uint8),
              "vertex_source": mesh.source.astype(np.int8),
              "replaced_tile": rr.zone_tile[rep].astype(np.int16), "replaced_row": rr.zone_row[rep].astype(np.int64)}
    with atomic_path(out_dir / "mesh.npz") as tmp:
        np.savez(tmp, **arrays)
    with atomic_path(out_dir / "fused.npz") as tmp:
        np.savez(tmp, xyz=geo.fused_xyz.astype(np.float32), source=geo.fused_source.astype(np.int8))
    if atlas is not None and atlas.image is not None:
        with atomic_path(out_dir / "atlas.jpg") as tmp:
            Image.fromarray(atlas.image).save(tmp, format="JPEG", quality=90)


# ----------------------------------------------------------------------------------------- for the merge

@dataclass(frozen=True)
class RegionMesh:
    """The part of one rebuilt region that falls in one tile (faces assigned by centroid, like the partition).

    region_id: the region's key (folder name); region_number: stable 31-bit number for provenance.
    vertices: (n, 3) float32 metres campus-local; vertex_ids: (n,) int64 (>= 0 original ids: weld these
    to the retained faces' vid columns; < 0: new, unique within the region); faces: (m, 3) int32 into
    vertices; uv: (m, 3, 2) float32 per-corner atlas coordinates (OBJ convention, NaN: untextured);
    atlas_path: the region's atlas image or None; face_colors: (m, 3) uint8 (use where uv is NaN);
    replaced_rows: (r,) int64 rows of this tile's faces.parquet that the region replaces (drop them);
    defect_type: the region's evidence verdict.
    """

    region_id: str
    region_number: int
    vertices: np.ndarray
    vertex_ids: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    atlas_path: Path | None
    face_colors: np.ndarray
    replaced_rows: np.ndarray
    defect_type: str = ""


def region_meshes_for_tile(wd: WorkDir | str | Path, tile: TileId | str) -> list[RegionMesh]:
    """Every rebuilt region's faces and replaced rows that belong to ``tile``, from the current plan.

    Only complete regions (region.json present, status "rebuilt") count; a region left to the mesh
    replaces nothing. A region that spans tiles appears in each, with that tile's faces only (its
    vertices at the tile border are repeated in both, with the same ids).
    """
    wd = wd if isinstance(wd, WorkDir) else WorkDir(wd)
    tile = tile if isinstance(tile, TileId) else TileId.from_key(tile)
    plan_file = plan_path(wd.root)
    if not plan_file.exists():
        return []
    doc = json.loads(plan_file.read_text())
    from storage.grid import PatchGrid

    g = doc["grid"]
    grid = PatchGrid(tuple(g["size_m"]), g["tile_size_m"], tuple(g["anchor_m"]))
    out = []
    for entry in doc["regions"]:
        if tile.key not in entry["tiles"]:
            continue
        d = region_dir(wd, entry["key"])
        try:
            meta = json.loads((d / "region.json").read_text())
        except (OSError, ValueError):
            continue
        if meta.get("status") != "rebuilt":
            continue
        with np.load(d / "mesh.npz") as z:
            arr = {k: z[k] for k in z.files}
        ftile = grid.tile_of_keys(arr["face_patch"])
        mine = (ftile[:, 0] == tile.ix) & (ftile[:, 1] == tile.iy)
        ti = meta["replaced_tiles"].index(tile.key) if tile.key in meta["replaced_tiles"] else -1
        rows = arr["replaced_row"][arr["replaced_tile"] == ti] if ti >= 0 else np.zeros(0, np.int64)
        if not mine.any() and not len(rows):
            continue
        f = arr["faces"][mine]
        used, inv = np.unique(f, return_inverse=True)
        atlas = d / meta["atlas"] if meta.get("atlas") else None
        out.append(RegionMesh(entry["key"], int(entry["number"]), arr["vertices"][used], arr["vertex_id"][used],
                              inv.reshape(-1, 3).astype(np.int32), arr["uv"][mine], atlas, arr["face_color"][mine],
                              np.sort(rows), meta.get("evidence", {}).get("type", "")))
    return out
