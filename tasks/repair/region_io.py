"""Reading a region's patches from the tile stores it lies in: the zone (patches to rebuild) and the context
ring, with the references (tile, row, uv, texture) needed to write the result back.

The on-disk format of a rebuilt region is :mod:`storage.contracts.region_mesh`; the plan, :mod:`storage.contracts.region_plan`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.contracts.region_plan import Region
from storage.grid import PatchGrid
from storage.ids import TileId
from storage.patches.remote_read import open_for_patches
from storage.vertex_ids import MISSING, local_ids
from tasks.geometry.holdout import Holdout
from tasks.regions import dilate
from tasks.repair.region_geometry import RegionInput

FACE_COLUMNS = [*(f"{a}{v}" for v in range(3) for a in "xyz"), "vid0", "vid1", "vid2", "nx", "ny", "nz",
                *(f"{a}{v}" for v in range(3) for a in "uv"), "texture", "red", "green", "blue"]
POINT_COLUMNS = ["x", "y", "z", "classification", "gps_time"]


@dataclass
class RegionRead:
    """What :func:`read_region` returns: the pure input plus the references needed to write back."""

    input: RegionInput
    zone_tile: np.ndarray  # (mz,) int16 index into tiles
    zone_row: np.ndarray  # (mz,) int64 row in that tile's faces.parquet
    zone_attrs: dict  # uv (mz, 3, 2), texture (mz,) global texture index, rgb (mz, 3)
    tiles: list[str]
    textures: list[str]  # texture image paths (global index)
    seconds: float
    held_out: int = 0  # MLS points of the region's patches held out of it (tasks.geometry.holdout)


def _kept_points(pd, holdout: Holdout | None, origin) -> tuple[np.ndarray, np.ndarray]:
    """A patch's points without the held-out strips: ((k, 3) float32 campus-local, (k,) bool kept rows)."""
    xyz = pd.xyz()
    if holdout is None or not holdout.enabled or not len(xyz):
        return xyz, np.ones(len(xyz), bool)
    keep = ~holdout.mask(pd.points["gps_time"], xyz[:, :2].astype(np.float64) + np.asarray(origin, np.float64)[:2])
    return xyz[keep], keep


def read_region(region: Region, grid: PatchGrid, tile_dir: Callable[[TileId], Path], origin,
                holdout: Holdout | None = None) -> RegionRead:
    """Read the region's rebuilt and context patches from every tile they lie in (and nothing else).

    grid: the campus patch grid; tile_dir(tile): the folder of a tile's store; origin: (3,) float64 world
    origin of the campus frame; holdout: the MLS strips the repair must not see (``quality.holdout_*``),
    left out of the zone's and the context's points (each patch is one patch of the rule).
    """
    t0 = time.perf_counter()
    want = np.concatenate([region.patches, region.context])
    tiles = grid.tile_of_keys(want)
    zone_parts, ctx_parts, pts_zone, cls_zone, pts_ctx = [], [], [], [], []
    ztile, zrow, uv, tex, rgb = [], [], [], [], []
    textures: list[str] = []
    tile_keys = []
    held_out = 0
    zone_set = frozenset(region.patches.tolist())
    for ti, (ix, iy) in enumerate(np.unique(tiles, axis=0).tolist()):
        tile = TileId(ix, iy)
        store = open_for_patches(tile_dir(tile))  # on a bucket: byte ranges of its tables
        tile_keys.append(tile.key)
        p = store.patches()
        sel = want[(tiles[:, 0] == ix) & (tiles[:, 1] == iy)]
        sel = sel[np.isin(sel, p["patch"])]
        tex_base = len(textures)
        textures += list(store.meta.textures)
        for pd in store.read_patches(sel.tolist(), POINT_COLUMNS, FACE_COLUMNS):
            f = pd.faces
            xyz, keep = _kept_points(pd, holdout, origin)
            held_out += int(len(keep) - keep.sum())
            if pd.key not in zone_set:
                ctx_parts.append(f)
                pts_ctx.append(xyz)
                continue
            zone_parts.append(f)
            pts_zone.append(xyz)
            cls_zone.append(pd.points["classification"][keep])
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
    if (vid == MISSING).any():  # a store without vertex ids: weld exactly coincident corners instead
        _, cid = np.unique(tri.reshape(-1, 3), axis=0, return_inverse=True)
        vid = np.where(vid == MISSING, local_ids(cid.reshape(vid.shape), "region_position"), vid)
    uid, first, inv = np.unique(vid.ravel(), return_index=True, return_inverse=True)
    xyz = tri.reshape(-1, 3)[first].astype(np.float64)
    faces = inv.reshape(-1, 3).astype(np.int64)
    mzn = len(zf["tri"])
    near = dilate(region.patches, 1)
    vkeys = grid.keys_local(xyz, origin)
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
                       "rgb": cat(rgb, (0, 3), np.uint8)}, tile_keys, textures, time.perf_counter() - t0, held_out)


def _concat_faces(parts: list[dict]) -> dict:
    if not parts or not sum(len(f["x0"]) for f in parts):
        return {"tri": np.zeros((0, 3, 3), np.float32), "vid": np.zeros((0, 3), np.int64),
                "n": np.zeros((0, 3), np.float32)}
    f = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    tri = np.stack([np.stack([f[f"{a}{v}"] for a in "xyz"], 1) for v in range(3)], 1)
    return {"tri": tri, "vid": np.stack([f[f"vid{v}"] for v in range(3)], 1),
            "n": np.stack([f["nx"], f["ny"], f["nz"]], 1)}
