"""On-disk format of a repaired region, reading a region's patches, and reading results back for the merge.

::

    regions/regions.json              the plan: one entry per region (key, number, patches, bad,
                                      context, tiles, parent), the grades source, the tiles' fingerprints
    regions/{key}/mesh.npz            the rebuilt mesh (format below); absent when the region is
                                      left to the mesh
    regions/{key}/fused.npz           the fused points: xyz (k, 3) float32 campus-local, source (k,)
                                      int8 (0 mesh vertex, 1 MLS point)
    regions/{key}/atlas.jpg           the region's texture atlas (absent when no image sees it)
    regions/{key}/region.json         status ("rebuilt" | "kept"), evidence (defect type), replaced
                                      tiles, figures; written last: its presence marks a complete region
    regions/_occupancy/{tile}.npz     MLS-occupied voxels of a tile (occluders for the texture stage)

``mesh.npz`` (numpy, uncompressed)::

    vertices      (n, 3) float32  metres, campus-local
    vertex_id     (n,)   int64    >= 0: an original mesh vertex id at its original position (border
                                  vertices: shared with the retained faces, weld by it); < 0: a new
                                  vertex (MLS point, or a seam vertex moved onto the MLS surface),
                                  unique within the region, not campus-wide
    vertex_source (n,)   int8     0 original mesh vertex, 1 MLS point, 2 Poisson vertex
    faces         (m, 3) int32    counter-clockwise seen from outside (like the input mesh)
    face_patch    (m,)   int64    patch key of each face's centroid (the partition's rule): the tile of
                                  a face is ``grid.tile_of_keys(face_patch)``
    uv            (m, 3, 2) float32 per-corner atlas coordinates, OBJ convention (origin bottom-left);
                                  NaN for a face no image sees
    face_color    (m, 3) uint8    colour of each face: the image colour, or the original mesh texture's
                                  colour where no image sees it (use it where uv is NaN)
    replaced_tile (r,)   int16    index into region.json "replaced_tiles"
    replaced_row  (r,)   int64    row in that tile's faces.parquet of each original face it replaces

The merge reads them through :func:`region_meshes_for_tile`.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path, file_fingerprint
from storage.ids import TileId
from storage.patch_store import PATCHES_FILE, PatchStore
from storage.workdir import WorkDir
from tasks.config import CampusConfig
from tasks.regions.plan import REGIONS_DIR, Region, plan_path

REGION_SCHEMA_VERSION = 1
FACE_COLUMNS = [*(f"{a}{v}" for v in range(3) for a in "xyz"), "vid0", "vid1", "vid2", "nx", "ny", "nz",
                *(f"{a}{v}" for v in range(3) for a in "uv"), "texture", "red", "green", "blue"]
POINT_COLUMNS = ["x", "y", "z", "classification"]


def region_dir(wd: WorkDir, key: str) -> Path:
    return wd.root / REGIONS_DIR / key


def tile_fingerprint(tile_dir: Path) -> str:
    """A tile store's identity for resume decisions: its patches.parquet (rewritten last on every partition)."""
    try:
        return file_fingerprint(tile_dir / PATCHES_FILE)
    except OSError:
        return "missing"


# ----------------------------------------------------------------------------------------- read

@dataclass
class RegionRead:
    """What :func:`read_region` returns: the pure input plus the references needed to write back."""

    input: object  # tasks.repair.geometry.RegionInput
    zone_tile: np.ndarray  # (mz,) int16 index into tiles
    zone_row: np.ndarray  # (mz,) int64 row in that tile's faces.parquet
    zone_attrs: dict  # uv (mz, 3, 2), texture (mz,) global texture index, rgb (mz, 3)
    tiles: list[str]
    textures: list[str]  # texture image paths (global index)
    seconds: float


def read_region(region: Region, cfg: CampusConfig, wd: WorkDir, frame) -> RegionRead:
    """Read the region's rebuilt and context patches from every tile they lie in (and nothing else)."""
    from tasks.regions.plan import dilate
    from tasks.repair.geometry import RegionInput

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


def merge_regions_for_tile(wd: WorkDir | str | Path, tile: TileId | str) -> list:
    """The rebuilt regions that reach into ``tile``, as the merge takes them (:class:`tasks.merge.region.RegionMesh`).

    Every face of such a region is handed over and the merge keeps those its tile owns (its rule is the
    one that decides, so a face near a tile border lands in exactly one tile); ``replaced_rows`` are the
    rows of this tile's faces table the region replaces. A region reaches into the tile when it owns a
    face there or replaces one of its faces.
    """
    from tasks.merge.region import RegionMesh as MergeRegion

    wd = wd if isinstance(wd, WorkDir) else WorkDir(wd)
    tile = tile if isinstance(tile, TileId) else TileId.from_key(tile)
    out = []
    for r in region_meshes_for_tile(wd, tile):
        d = region_dir(wd, r.region_id)
        with np.load(d / "mesh.npz") as z:
            arr = {k: z[k] for k in ("vertices", "vertex_id", "faces", "uv", "face_color")}
        fp = file_fingerprint(d / "mesh.npz") + ":" + file_fingerprint(d / "region.json")
        if r.atlas_path is not None:
            fp += ":" + file_fingerprint(r.atlas_path)
        out.append(MergeRegion(region=r.region_number, vertices=arr["vertices"].astype(np.float32),
                               faces=arr["faces"].astype(np.int64), replaced_patches=np.zeros(0, np.int64),
                               vertex_ids=arr["vertex_id"].astype(np.int64),
                               atlas=None if r.atlas_path is None else str(r.atlas_path),
                               corner_uv=arr["uv"].astype(np.float32), face_colors=arr["face_color"].astype(np.uint8),
                               replaced_rows=r.replaced_rows.astype(np.int64), fingerprint=f"{tile.key}:{fp}"))
    return out
