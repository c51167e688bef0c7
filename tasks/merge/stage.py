"""Merge: per ground tile, the retained mesh and the rebuilt regions become one clean :class:`TileMesh`.

Inputs of tile T (``tiles/{ix}_{iy}/``): the patch store's faces (corners inline, campus vertex ids,
per-corner uv, texture index), the patch grades (``grades.parquet``; else the labels; else unknown),
and the rebuilt regions that reach into T (repair's output, any objects with the attributes of
:class:`RebuiltRegion`; none until repair runs). Output: ``tiles/{ix}_{iy}/merged.npz`` + ``merged.json``
(:mod:`storage.tile_mesh`), the input of export.
The repair contract is in :mod:`tasks.merge.region`, soups and their weld in :mod:`tasks.merge.soup`.

Rules:

- **Retained** faces are the store faces of T whose patch no region replaces (and which no region
  names in ``replaced_faces``). They keep the original texture: the tile's texture list references
  the input atlases by path (nothing is copied) and uv become per-vertex.
- **Rebuilt** faces are the region faces whose centroid lies in a patch of T (the rule that assigns a
  store face to its tile), so a face belongs to exactly one tile even when its region spans several.
  They take their region's atlas (or its vertex colours) and provenance (grade bad, source rebuilt,
  region id).
- Corners are **welded by vertex id** (:mod:`tasks.merge.weld`): a rebuilt region that gives its kept
  border vertices their campus vertex ids (``vertex_ids``) is closed to the retained mesh exactly,
  whatever the float noise; a vertex is split only where its corners differ in texture, uv or colour.
  Where a region moved a kept vertex, the retained position wins (the retained faces come first).
- **No face twice**: a face on the same three vertices as an earlier face (either orientation) is
  dropped, and so is a face with two corners on one vertex.

Memory is bounded by the tile (one store, the regions touching it). The stage
:func:`run_merge_tile` is resumable: its fingerprint is the tile's store, its grade/label table, the
campus frame and the rebuilt regions touching it; an unchanged result is not rewritten, so export's
fingerprint of the tile (the file's bytes) does not change either.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.atomic import file_fingerprint, file_sha256
from storage.errors import EmptyTileError, InputError
from storage.grid import PatchGrid
from storage.ids import TileId
from storage.manifest import combine_fingerprints
from storage.patch_store import PATCHES_FILE, PatchStore, side_table_path
from storage.tile_mesh import GRADE_UNKNOWN, TileMesh, tile_mesh_paths, write_tile_mesh
from storage.workdir import STALE_FILE, WorkDir, campus_frame, read_campus
from tasks.merge.region import RebuiltRegion, RegionMesh
from tasks.merge.soup import FaceSoup, WeldStats, concat_soups, region_soup, store_soup, weld_soup
from tasks.units import Done, run_unit

__all__ = ["FaceSoup", "MergeStats", "RebuiltRegion", "RegionMesh", "faces_in_tile", "merge_tile", "retained_soup",
           "run_merge_tile", "weld_soup"]

STORE_FACE_COLUMNS = ([f"{a}{v}" for v in range(3) for a in "xyz"] + [f"vid{v}" for v in range(3)]
                      + [f"{a}{v}" for v in range(3) for a in "uv"]
                      + ["texture", "red", "green", "blue", "src_face", "source", "patch"])  # fmt: skip

# ------------------------------------------------------------------------------ one tile, pure


def faces_in_tile(xyz: np.ndarray, grid: PatchGrid, origin, tile: TileId) -> tuple[np.ndarray, np.ndarray]:
    """Which faces belong to ``tile`` by the store's rule (the tile holding the centre of the patch
    holding the face centroid). xyz: (m, 3, 3) float32 campus-local; origin: (3,) float64 world.
    Returns ((m,) bool, (m,) int64 patch key of each face)."""
    if len(xyz) == 0:
        return np.zeros(0, bool), np.zeros(0, np.int64)
    cells = grid.face_cells([xyz[:, v, a] for v in range(3) for a in range(3)], origin)
    t = grid.tile_of_cells(cells)
    return (t[:, 0] == tile.ix) & (t[:, 1] == tile.iy), grid.pack(cells)


@dataclass(frozen=True)
class MergeStats:
    """What one tile's merge did: faces of the store retained / replaced, rebuilt faces taken (and
    how many of them lie in a patch whose original faces were retained: a sign that a region overlaps
    the retained mesh), the weld's counts, regions used."""

    retained_faces: int
    replaced_faces: int
    rebuilt_faces: int
    rebuilt_in_retained_patches: int
    weld: WeldStats
    regions: tuple[int, ...] = field(default_factory=tuple)

    def to_json(self) -> dict:
        return {"retained_faces": self.retained_faces, "replaced_faces": self.replaced_faces,
                "rebuilt_faces": self.rebuilt_faces, "rebuilt_in_retained_patches": self.rebuilt_in_retained_patches,
                "faces": self.weld.faces_out, "vertices": self.weld.vertices,
                "duplicates_dropped": self.weld.duplicates, "degenerate_dropped": self.weld.degenerate,
                "split_vertices": self.weld.split_vertices, "regions": list(self.regions)}  # fmt: skip


def retained_soup(cols: dict[str, np.ndarray], face_grade: np.ndarray, regions: Sequence[RegionMesh]
                  ) -> tuple[FaceSoup, np.ndarray, int]:
    """The store faces of a tile that no region replaces.

    cols: the tile's store face columns (:data:`STORE_FACE_COLUMNS`), (m,) each; face_grade: (m,) int8
    grade of each row's patch; regions: the rebuilt regions reaching into the tile.
    Returns (their soup, (r,) int64 sorted keys of the patches holding them, number of faces replaced).
    """
    patch = cols["patch"]
    replaced = np.zeros(len(patch), bool)
    if regions:
        replaced = np.isin(patch, np.concatenate([r.replaced_patches for r in regions]))
        named = [r.replaced_faces for r in regions if r.replaced_faces is not None and len(r.replaced_faces)]
        if named:
            pairs = np.concatenate(named)
            face_key = (cols["source"].astype(np.int64) << 32) | cols["src_face"]
            replaced |= np.isin(face_key, (pairs[:, 0] << 32) | pairs[:, 1])
        for r in regions:
            if r.replaced_rows is not None and len(r.replaced_rows):
                if r.replaced_rows.min() < 0 or r.replaced_rows.max() >= len(patch):
                    raise InputError(None, f"rebuilt region {r.region} replaces rows outside the tile's faces "
                                     "(the region is older than the store: rerun the repair)")
                replaced[r.replaced_rows] = True
    if not replaced.any():
        return store_soup(cols, face_grade), np.unique(patch), 0
    keep = np.flatnonzero(~replaced)
    return (store_soup({k: v[keep] for k, v in cols.items()}, face_grade[keep]), np.unique(patch[keep]),
            int(replaced.sum()))


def merge_tile(tile: TileId, retained: FaceSoup, retained_patches: np.ndarray, textures: Sequence[str],
               regions: Sequence[RegionMesh], grid: PatchGrid, origin, replaced_faces: int = 0
               ) -> tuple[TileMesh, MergeStats]:
    """One tile's merged mesh: the retained faces (:func:`retained_soup`) and the faces of ``regions``
    that the tile owns (:func:`faces_in_tile`), welded (:func:`weld_soup`).

    textures: the store's texture paths (what ``retained.texture`` indexes); regions: the rebuilt
    regions reaching into the tile (any order); grid, origin: the campus patch grid and (3,) float64
    world origin; replaced_faces: carried into the stats. Raises EmptyTileError when no face is left.
    """
    regions = sorted(regions, key=lambda r: r.region)
    if len({r.region for r in regions}) != len(regions):
        raise InputError(None, f"tile {tile.key}: two rebuilt regions with one region number")
    all_textures = list(textures)
    parts, rebuilt, overlap = [retained], 0, 0
    for r in regions:
        index = -1
        if r.atlas is not None:
            if r.atlas not in all_textures:
                all_textures.append(r.atlas)
            index = all_textures.index(r.atlas)
        soup = region_soup(r, index)
        own, face_patch = faces_in_tile(soup.xyz, grid, origin, tile)
        if own.any():
            rows = np.flatnonzero(own)
            parts.append(soup.take(rows))
            rebuilt += len(rows)
            overlap += int(np.isin(face_patch[rows], retained_patches).sum())
    soup = concat_soups(parts) if len(parts) > 1 else retained
    if soup.n_faces == 0:
        raise EmptyTileError(None, f"tile {tile.key}: no faces left after merging")
    mesh, weld = weld_soup(tile.key, soup, all_textures)
    if mesh.n_faces == 0:
        raise EmptyTileError(None, f"tile {tile.key}: every face is degenerate")
    return mesh, MergeStats(retained.n_faces, replaced_faces, rebuilt, overlap, weld, tuple(r.region for r in regions))


def _read_retained(store: PatchStore, regions: Sequence[RegionMesh]) -> tuple[FaceSoup, np.ndarray, int, str]:
    """Read a tile store's faces and keep the retained ones (the columns are freed on return)."""
    grade, grade_source = patch_grades(store)
    counts = store.patches()["n_faces"].astype(np.int64)
    if counts.sum() != store.n_faces:
        raise InputError(store.tile_dir / PATCHES_FILE, "face counts do not add up to the faces table")
    _, cols = store.read_all(point_columns=[], face_columns=STORE_FACE_COLUMNS)
    retained = retained_soup(cols, np.repeat(grade, counts), regions)
    del cols
    import pyarrow as pa  # the reader's buffers are free now: give them back before the weld (-20 % peak RSS)

    pa.default_memory_pool().release_unused()
    return (*retained, grade_source)


# ------------------------------------------------------------------------------ stage

MERGE_STAGE = "merge"
RegionSource = Callable[[WorkDir, TileId], Sequence[RebuiltRegion]]


def patch_grades(store: PatchStore) -> tuple[np.ndarray, str]:
    """(u,) int8 grade per patch of the store (0 good, 1 bad, -1 unknown) and where it came from:
    "grades" (classify), "labels" (truth labels), or "none" (all unknown)."""
    keys = store.patches()["patch"]
    grades = store.side("grades")
    if grades is not None:
        return grades["grade"].astype(np.int8), "grades"
    labels = store.side("labels")
    if labels is not None:
        return labels["label"].astype(np.int8), "labels"
    return np.full(len(keys), GRADE_UNKNOWN, np.int8), "none"


def remove_merged(tile_dir: Path) -> None:
    """Remove a tile's merged mesh (the .json, which marks it complete, first)."""
    npz, meta = tile_mesh_paths(tile_dir)
    meta.unlink(missing_ok=True)
    npz.unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        tile_dir.rmdir()  # only when nothing else is left in it


def _same_on_disk(tile_dir: Path, mesh: TileMesh) -> bool:
    """Whether tile_dir already holds exactly ``mesh`` (then it is not rewritten). Reads the old arrays
    one at a time, stopping at the first difference, so it costs at most one array of memory."""
    npz, meta = tile_mesh_paths(tile_dir)
    try:
        doc = json.loads(meta.read_text())
        textures = [str((tile_dir / t).resolve()) for t in doc["textures"]]
        if doc.get("tile") != mesh.tile or textures != [str(Path(t).resolve()) for t in mesh.textures]:
            return False
        with np.load(npz, allow_pickle=False) as z:
            for name in ("faces", "face_texture", "grade", "source", "region", "vertices", "uv", "vertex_colors"):
                new = getattr(mesh, name)
                if (new is None) != (name not in z.files) or (new is not None and not np.array_equal(z[name], new)):
                    return False
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return False
    return True


def _side_fingerprint(tile_dir: Path) -> str:
    for name in ("grades", "labels"):
        p = side_table_path(tile_dir, name)
        if p.exists():
            return f"{name}:{file_sha256(p)}"
    return "none"


def merge_fingerprint(tile_dir: Path, regions: Sequence[RegionMesh], frame_json: dict) -> str:
    """The identity of a tile's merge inputs: store files, grades (or labels), frame, rebuilt regions."""
    store = [file_fingerprint(tile_dir / n) for n in ("faces.parquet", PATCHES_FILE)]
    regs = [f"{r.region}:{r.content_fingerprint()}" for r in sorted(regions, key=lambda r: r.region)]
    return combine_fingerprints([*store, _side_fingerprint(tile_dir), repr(sorted(frame_json.items())), *regs])


def run_merge_tile(tile: TileId, cfg, wd: WorkDir, regions: RegionSource | Sequence | None = None) -> dict | None:
    """Merge one tile into ``tiles/{ix}_{iy}/merged.npz`` + ``merged.json``.

    cfg: the CampusConfig (its patch grid decides which tile owns a rebuilt face). regions: repair's
    ``region_meshes_for_tile`` (called as ``regions(wd, tile)``), or the list itself; None before repair.
    Returns the unit summary (status done / empty / failed, counts, ``rewritten``), or None when there is
    nothing to do: a tile without a store loses its merged mesh; a stale store (its input failed) keeps
    its last good one.
    """
    tile_dir = wd.tile_dir(tile)
    if not (tile_dir / PATCHES_FILE).exists():
        remove_merged(tile_dir)
        return None
    if (tile_dir / STALE_FILE).exists():
        return None
    try:
        found = regions(wd, tile) if callable(regions) else (regions or [])
        region_list = [RegionMesh.of(r) for r in found]
        frame_json = read_campus(wd)["frame"]
        fp = merge_fingerprint(tile_dir, region_list, frame_json)
    except (InputError, ValueError, OSError) as e:
        return {"unit": tile.key, "status": "failed", "error": f"tile {tile.key}: merge inputs: {e}", "skipped": False}
    grid = cfg.grid()

    def work() -> Done:
        t0 = time.perf_counter()
        store = PatchStore(tile_dir)
        retained, retained_patches, n_replaced, grade_source = _read_retained(store, region_list)
        frame = campus_frame({"frame": frame_json})
        mesh, stats = merge_tile(tile, retained, retained_patches, store.meta.textures, region_list, grid,
                                 frame.origin_array, n_replaced)
        del retained
        for t in mesh.textures:
            if not Path(t).is_file():
                raise InputError(t, f"texture image of tile {tile.key} not found")
        rewritten = not _same_on_disk(tile_dir, mesh)
        if rewritten:
            write_tile_mesh(tile_dir, mesh)
        npz, meta = tile_mesh_paths(tile_dir)
        summary = {"tile": tile.key, **stats.to_json(), "grades_from": grade_source, "textures": len(mesh.textures),
                   "rewritten": rewritten, "merge_seconds": time.perf_counter() - t0,
                   "worker": f"{socket.gethostname()}:{os.getpid()}"}  # fmt: skip
        return Done(outputs=[str(p.relative_to(wd.root)) for p in (npz, meta)], summary=summary)

    res = run_unit(wd, MERGE_STAGE, tile.key, fp, {"grid": grid.to_json()}, work)
    if res.get("status") == "empty":
        remove_merged(tile_dir)
    return res
