"""The ingest stage's I/O: route one unit's points or faces to staging files per ground tile.

An ingest unit is one mesh file, or one range of ``tiling.chunk_points`` points of a cloud file
(:mod:`tasks.ingest.plan`), of which only the points in ``inputs.points_bounds`` are routed (a COPC file
decompresses only its octree nodes over that box); its staging runs follow the contract of :mod:`storage.contracts.staging`. A unit that
fails removes what it had written, and a unit that is redone first removes its previous output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.contracts.columns import write_run
from storage.contracts.staging import remove_unit_runs, run_name
from storage.errors import InputError
from storage.formats.meshes import read_mesh
from storage.formats.points import iter_points, iter_points_range
from storage.frame import CampusFrame
from storage.grid import PatchGrid
from storage.inputs.remote import local_input, staged_ref
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.geometry.cells import partition_cells
from tasks.geometry.tiling import group_by_tile
from tasks.geometry.triangles import face_normals
from tasks.ingest.kernels import (
    face_columns,
    point_columns,
    split_mesh_faces,
    to_campus,
    vertex_ids,
    weld_vertex_index,
)
from tasks.ingest.plan import LAS_SUFFIXES, IngestUnit
from tasks.scan import mesh_placement, place_mesh
from tasks.units import Done, run_unit


def _remove(wd: WorkDir, rel: list[str]) -> None:
    """Remove the files ``rel`` (paths relative to the work dir)."""
    for r in rel:
        (wd.root / r).unlink(missing_ok=True)


def _route_points(unit: IngestUnit, cfg: CampusConfig, frame: CampusFrame, matrix: np.ndarray,
                  wd: WorkDir, outputs: list[str], tiles: dict) -> None:
    """Route a point range chunk by chunk (registered by ``matrix``); appends written paths to ``outputs``
    and rows per tile key to ``tiles``."""
    grid = cfg.grid()
    src = local_input(unit.path)  # an input by URL is read from a staged copy
    box = None if unit.bounds is None else [unit.bounds[:2], unit.bounds[2:]]  # a COPC reads its nodes over it
    if Path(unit.path).suffix.lower() in LAS_SUFFIXES:
        chunks = iter_points_range(src, unit.start, unit.stop, cfg.tiling.chunk_points, cfg.inputs.units_scale,
                                   bounds=box)
    else:
        chunks = iter_points(src, cfg.tiling.chunk_points, cfg.inputs.units_scale, bounds=box)
    n = 0
    for k, chunk in enumerate(chunks):
        local64 = to_campus(chunk.xyz, frame, matrix, unit.path)
        cells = grid.cells_local(local64, frame.origin)
        cols = point_columns(chunk, local64.astype(np.float32), unit.source)
        del local64
        cols["patch"] = grid.pack(cells)
        _write_runs(wd, unit.key, k, cols, cells, grid, None, outputs, tiles)
        n += len(chunk)
    if n == 0 and box is None:  # with a box, a range may well lie outside it
        raise InputError(unit.path, f"no points in range [{unit.start}, {unit.stop})")


def _route_mesh(unit: IngestUnit, cfg: CampusConfig, frame: CampusFrame, wd: WorkDir,
                outputs: list[str], tiles: dict) -> dict:
    """Route a whole mesh file's faces (with welded vertex ids, normals and corner patches); returns the
    mesh's clean-up counts."""
    grid = cfg.grid()
    placement = mesh_placement(unit.path, cfg)  # a production's metadata.xml, else inputs.mesh_offset
    local = local_input(unit.path, siblings=True)
    mesh = place_mesh(read_mesh(local, offset=placement.offset, units_scale=cfg.inputs.units_scale), placement, local)
    vids = vertex_ids(unit.source, mesh.faces, weld_vertex_index(mesh.vertices), mesh.vertices, placement.seam_key)
    normals = face_normals(mesh.vertices, mesh.faces)
    local64 = to_campus(mesh.vertices, frame, None, unit.path)
    n_in = mesh.n_faces
    # faces longer than the smallest patch side are split, so every patch a coarse surface crosses holds
    # its part (tasks.geometry.split); pieces keep their face's normal, texture and src_face
    mesh, tri64, vids, parent = split_mesh_faces(mesh, local64[mesh.faces], vids, min(grid.size_m))
    normals = normals[parent]
    corners = tri64.reshape(-1, 3)  # Algorithm 1 step 3: patch of each corner vertex
    vkeys = grid.pack(grid.cells_local(corners, frame.origin)).reshape(-1, 3)
    cells = grid.face_cells([tri64[:, v, a] for v in range(3) for a in range(3)], frame.origin)
    cols = face_columns(mesh, tri64.astype(np.float32), vids, normals, unit.source, src_face=parent)
    cols["patch"] = grid.pack(cells)
    for v in range(3):
        cols[f"vp{v}"] = vkeys[:, v]
    meta = {"textures": [staged_ref(t, unit.path) for t in mesh.textures], "source": unit.path,
            "n_degenerate_dropped": mesh.n_degenerate_dropped, "n_duplicate_dropped": mesh.n_duplicate_dropped}
    _write_runs(wd, unit.key, 0, cols, cells, grid, meta, outputs, tiles)
    return {"n_degenerate_dropped": mesh.n_degenerate_dropped, "n_duplicate_dropped": mesh.n_duplicate_dropped,
            "n_nonmanifold_edges": mesh.n_nonmanifold_edges,
            "n_faces_split": int(np.count_nonzero(np.bincount(parent, minlength=n_in) > 1)),
            "n_faces_added": int(len(parent) - n_in)}


def _write_runs(wd: WorkDir, key: str, part: int, cols: dict, cells: np.ndarray, grid: PatchGrid,
                meta: dict | None, outputs: list[str], tiles: dict) -> None:
    """Route rows to their tiles as sorted runs (``staging/{tile}/{key}-{part:03d}.arrow``, sorted by patch,
    stable), which the partition stage merges without sorting a whole tile in memory. cells: (n, 3) int64."""
    order = partition_cells(cells).order  # stable by patch key
    for tile, idx in group_by_tile(grid.tile_of_cells(cells)[order]):  # stable: each tile stays key-sorted
        rows = order[idx]
        out = wd.staging_dir(tile) / run_name(key, part)
        write_run(out, {c: v[rows] for c, v in cols.items()}, meta)
        outputs.append(str(out.relative_to(wd.root)))
        tiles[tile.key] = tiles.get(tile.key, 0) + len(rows)


def ingest_fingerprint(unit: IngestUnit, frame: CampusFrame, matrix: np.ndarray | None) -> str:
    """A unit's input identity: its key, content, range, the campus frame and (points) the registration and
    the points box."""
    parts = [unit.key, unit.fingerprint, f"{unit.start}:{unit.stop}", str(frame.to_json())]
    if unit.kind == "points":
        parts.append(np.asarray(matrix, np.float64).tobytes().hex())
        if unit.bounds is not None:
            parts.append(np.asarray(unit.bounds, np.float64).tobytes().hex())
    return combine_fingerprints(parts)


def run_ingest_unit(unit: IngestUnit, cfg: CampusConfig, wd: WorkDir, frame: CampusFrame,
                    matrix: np.ndarray | None) -> dict:
    """Route one unit's points or faces to staging files per tile (skipped when done and unchanged).

    matrix: (4, 4) registration for point units (None for meshes, which define the frame).
    """
    def work() -> Done:
        remove_unit_runs(wd, unit.key)  # a redone unit starts clean
        outputs: list[str] = []
        tiles: dict[str, int] = {}
        try:
            extra = (_route_points(unit, cfg, frame, matrix, wd, outputs, tiles) if unit.kind == "points"
                     else _route_mesh(unit, cfg, frame, wd, outputs, tiles)) or {}
        except BaseException:
            _remove(wd, outputs)  # a failed unit leaves nothing for partition to read
            raise
        return Done(outputs=outputs, summary={"kind": unit.kind, "rows": int(sum(tiles.values())),
                                              "tiles": tiles, **extra})

    return run_unit(wd, "ingest", unit.key, ingest_fingerprint(unit, frame, matrix), cfg.stage_params("ingest"), work)
