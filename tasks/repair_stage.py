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
        if d.is_dir() and d.name not in names:
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
