"""Merge: per ground tile, the retained mesh and the rebuilt regions become one clean :class:`TileMesh`.

Inputs of tile T (``tiles/{ix}_{iy}/``): the patch store's faces (corners inline, campus vertex ids,
per-corner uv, texture index), the patch grades under ``repair.grades``
(:func:`storage.patches.state.patch_grades`, the rule the regions stage plans by, so merge marks bad
exactly what repair was asked to rebuild), and the rebuilt regions that reach into T
(:func:`storage.contracts.region_mesh.region_meshes_for_tile`; none until repair runs). Output:
``tiles/{ix}_{iy}/merged.npz`` + ``merged.json`` (:mod:`storage.contracts.tile_mesh`), the input of export. The
pure merge is in :mod:`tasks.merge.tile`, soups and their weld in :mod:`tasks.merge.soup`.

Rules:

- **Retained** faces are the store faces of T whose patch or row no region replaces. They keep the
  original texture: the tile's texture list references the input atlases by path (nothing is copied)
  and uv become per-vertex. They carry their patch's grade (under ``repair.grades``).
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

Memory is bounded by the tile: the regions touching it are loaded only in a unit that runs and dropped
once their owned faces are taken, the retained soup once concatenated, so the weld holds one soup. The
stage :func:`run_merge_tile` is resumable: its fingerprint is the tile's store, the grade table it reads
(or "all"), the campus frame and the files of the rebuilt regions the plan lists for the tile
(:func:`storage.contracts.region_mesh.region_files_for_tile`: a stat and two small reads each, no mesh loaded, so
deciding that a tile is up to date costs no array read); an unchanged result is not rewritten, so
export's fingerprint of the tile (the file's bytes) does not change either.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import time
import zipfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import file_fingerprint
from storage.contracts.region_mesh import RegionMesh, region_files_for_tile, region_meshes_for_tile
from storage.contracts.tile_mesh import TileMesh, texture_refs, tile_mesh_paths, write_tile_mesh
from storage.errors import InputError
from storage.ids import TileId
from storage.inputs.remote import input_exists
from storage.objstore.store import redact
from storage.patches.read import PatchStore
from storage.patches.schema import FACES_FILE, PATCHES_FILE, POINTS_FILE, side_table_path
from storage.patches.state import grades_identity, patch_grades
from storage.workdir.layout import STALE_FILE, WorkDir, campus_frame, read_campus
from storage.workdir.manifest import combine_fingerprints
from tasks.merge.face_quality import DEVIATION_MAX_POINTS, with_face_quality
from tasks.merge.soup import FaceSoup, concat_soups
from tasks.merge.tile import STORE_FACE_COLUMNS, rebuilt_parts, retained_soup, weld_tile
from tasks.units import Done, run_unit

MERGE_STAGE = "merge"


def _read_retained(store: PatchStore, regions: Sequence[RegionMesh], grades_mode: str
                   ) -> tuple[FaceSoup, np.ndarray, int, str]:
    """Read a tile store's faces and keep the retained ones, graded under ``grades_mode`` (the columns are
    freed on return). Returns (their soup, (r,) int64 keys of their patches, faces replaced, grades source)."""
    _, grade, grade_source = patch_grades(store, grades_mode)
    counts = store.patches()["n_faces"].astype(np.int64)
    if counts.sum() != store.n_faces:
        raise InputError(store.tile_dir / PATCHES_FILE, "face counts do not add up to the faces table")
    _, cols = store.read_all(point_columns=[], face_columns=STORE_FACE_COLUMNS)
    retained = retained_soup(cols, np.repeat(grade, counts), regions)
    del cols
    _give_back_freed_memory()
    return (*retained, grade_source)


def _give_back_freed_memory() -> None:
    """Return freed buffers to the OS before the next peak: Arrow's pool, and glibc's heap, which keeps
    the many freed column-sized (< 32 MiB) arrays otherwise (-150 MB of the demo's largest tile)."""
    import ctypes

    import pyarrow as pa

    pa.default_memory_pool().release_unused()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").malloc_trim(0)


def remove_merged(tile_dir: Path) -> None:
    """Remove a tile's merged mesh (the .json, which marks it complete, first)."""
    npz, meta = tile_mesh_paths(tile_dir)
    recorded.unlink(meta)
    recorded.unlink(npz)
    with contextlib.suppress(OSError):
        tile_dir.rmdir()  # only when nothing else is left in it


def _same_on_disk(tile_dir: Path, mesh: TileMesh) -> bool:
    """Whether tile_dir already holds exactly ``mesh`` (then it is not rewritten). Reads the old arrays
    one at a time, stopping at the first difference, so it costs at most one array of memory."""
    npz, meta = tile_mesh_paths(tile_dir)
    try:
        doc = json.loads(meta.read_text())
        textures = texture_refs(tile_dir, doc["textures"])
        if doc.get("tile") != mesh.tile or textures != texture_refs(Path.cwd(), mesh.textures):
            return False
        with np.load(npz, allow_pickle=False) as z:
            for name in ("faces", "face_texture", "grade", "source", "region", "vertices", "uv", "vertex_colors",
                         "face_deviation", "face_score"):
                new = getattr(mesh, name)
                if (new is None) != (name not in z.files) or (
                        new is not None and not np.array_equal(z[name], new, equal_nan=new.dtype.kind == "f")):
                    return False
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile):
        return False
    return True


def merge_fingerprint(tile_dir: Path, regions: Sequence[tuple[int, str]], frame_json: dict, grades_mode: str) -> str:
    """The identity of a tile's merge inputs: store files, the grades it reads under ``grades_mode``
    (:func:`storage.patches.state.grades_identity`), frame, and the rebuilt regions as (number, content
    fingerprint) pairs (:func:`storage.contracts.region_mesh.region_files_for_tile`: the files, no array read)."""
    store = [file_fingerprint(tile_dir / n) for n in (FACES_FILE, PATCHES_FILE, POINTS_FILE)]
    grades = side_table_path(tile_dir, "grades")  # the faces' scores, whatever table their grades come from
    store.append(file_fingerprint(grades) if recorded.is_file(grades) else "no grades")
    regs = [f"{number}:{fp}" for number, fp in sorted(regions)]
    return combine_fingerprints([*store, grades_identity(tile_dir, grades_mode), repr(sorted(frame_json.items())),
                                 *regs])


def _load_regions(root: Path, tile: TileId) -> list[RegionMesh]:
    """The rebuilt regions reaching into ``tile``, loaded (only in a unit that runs); a region file that
    cannot be read is this tile's InputError."""
    try:
        return region_meshes_for_tile(root, tile)
    except (ValueError, KeyError, zipfile.BadZipFile) as e:
        raise InputError(None, f"tile {tile.key}: merge inputs: a rebuilt region: {e}") from None


def _face_quality(store: PatchStore, mesh: TileMesh, grid, origin) -> tuple[TileMesh, dict]:
    """The merged mesh with its per-face scan-to-model distance and grader score
    (:func:`tasks.merge.face_quality.with_face_quality`), from the tile's points and ``grades.parquet``."""
    points, stride = thinned_points(store)
    grades = store.side("grades")
    keys = store.patches()["patch"]
    return with_face_quality(mesh, points, keys, None if grades is None else grades["score"], grid, origin, stride)


def thinned_points(store: PatchStore, max_points: int = DEVIATION_MAX_POINTS, window: int = 4_000_000
                   ) -> tuple[np.ndarray, int]:
    """(every ``stride``-th point of the tile (k, 3) float32, at most ``max_points``; stride), read ``window``
    rows at a time: memory is bounded by the window, not the tile (a 70 M-point tile read whole took 2.7 GB)."""
    n = int(store.n_points)
    if n == 0:
        return np.zeros((0, 3), np.float32), 1
    stride = max(1, -(-n // max_points))
    if stride == 1:
        return store.read_all_stacked("points", ["x", "y", "z"]), 1
    parts = []
    for lo in range(0, n, window):
        block = store.read_rows_stacked("points", ["x", "y", "z"], lo, min(lo + window, n))
        parts.append(block[(-lo) % stride::stride].copy())  # global rows 0, stride, 2 stride, ...
        del block
    return np.concatenate(parts), stride


def _merge_work(tile: TileId, cfg, wd: WorkDir, frame_json: dict, regions: Sequence[RegionMesh] | None) -> Done:
    """The unit's work. Drops each input once used (the regions once their owned faces are taken, the
    retained soup once concatenated), so the weld, the peak, holds only the tile's soup."""
    t0 = time.perf_counter()
    tile_dir, grid = wd.tile_dir(tile), cfg.grid()
    region_list = _load_regions(wd.root, tile) if regions is None else list(regions)
    store = PatchStore(tile_dir)
    retained, retained_patches, n_replaced, grade_source = _read_retained(store, region_list, cfg.repair.grades)
    frame = campus_frame({"frame": frame_json})
    rebuilt = rebuilt_parts(tile, region_list, store.meta.textures, grid, frame.origin_array, retained_patches)
    del region_list, retained_patches
    n_retained = retained.n_faces
    if rebuilt.parts:
        retained = concat_soups([retained, *rebuilt.parts])
        rebuilt.parts.clear()
    _give_back_freed_memory()
    mesh, stats = weld_tile(tile, retained, rebuilt, n_retained, n_replaced)
    del retained
    mesh, quality = _face_quality(store, mesh, grid, frame.origin_array)
    for t in mesh.textures:
        if not input_exists(t):
            raise InputError(redact(t), f"texture image of tile {tile.key} not found")
    rewritten = not _same_on_disk(tile_dir, mesh)
    if rewritten:
        write_tile_mesh(tile_dir, mesh)
    npz, meta = tile_mesh_paths(tile_dir)
    summary = {"tile": tile.key, **stats.to_json(), **quality, "grades_from": grade_source, "textures": len(mesh.textures),
               "rewritten": rewritten, "merge_seconds": time.perf_counter() - t0,
               "worker": f"{socket.gethostname()}:{os.getpid()}"}  # fmt: skip
    return Done(outputs=[str(p.relative_to(wd.root)) for p in (npz, meta)], summary=summary)


def run_merge_tile(tile: TileId, cfg, wd: WorkDir, regions: Sequence[RegionMesh] | None = None) -> dict | None:
    """Merge one tile into ``tiles/{ix}_{iy}/merged.npz`` + ``merged.json``.

    cfg: the CampusConfig (its patch grid decides which tile owns a rebuilt face; ``repair.grades`` which
    grades the faces carry). regions: the rebuilt regions reaching into the tile; None (the stage's use):
    read from the work dir, fingerprinted by their files (:func:`storage.contracts.region_mesh.region_files_for_tile`)
    and loaded only when the unit runs (:func:`storage.contracts.region_mesh.region_meshes_for_tile`). Returns the
    unit summary (status done / empty / failed, counts, ``grades_from``, ``rewritten``), or None when
    there is nothing to do: a tile without a store loses its merged mesh; a stale store (its input
    failed) keeps its last good one.
    """
    tile_dir = wd.tile_dir(tile)
    if not recorded.is_file(tile_dir / PATCHES_FILE):  # on a bucket: recorded, maybe not downloaded
        remove_merged(tile_dir)
        return None
    if recorded.is_file(tile_dir / STALE_FILE):
        return None
    try:
        if regions is None:
            ids = [(f.region, f.fingerprint) for f in region_files_for_tile(wd.root, tile)]
        else:
            ids = [(r.region, r.content_fingerprint()) for r in regions]
        frame_json = read_campus(wd)["frame"]
        fp = merge_fingerprint(tile_dir, ids, frame_json, cfg.repair.grades)
    except (InputError, ValueError, OSError) as e:
        return {"unit": tile.key, "status": "failed", "error": f"tile {tile.key}: merge inputs: {e}", "skipped": False}
    res = run_unit(wd, MERGE_STAGE, tile.key, fp, {"grid": cfg.grid().to_json()},
                   lambda: _merge_work(tile, cfg, wd, frame_json, regions))
    if res.get("status") == "empty":
        remove_merged(tile_dir)
    return res
