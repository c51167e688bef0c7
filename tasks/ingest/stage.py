"""Ingest: convert the inputs to the campus frame and route points and faces to their ground tiles.

An ingest unit is one mesh file, or one range of ``tiling.chunk_points`` points of a cloud file. Its key
is the input's identity, never a list position: ``{m|p}{source:08x}-{fingerprint[:8]}-{range:05d}``
(stable source id of the path, content fingerprint, range number). Routing writes *staging* files
``staging/{tile}/{unit key}-{part:03d}.parquet``, which the partition stage of that tile reads.

So the set of staging files is a function of the inputs: before partition, :func:`prune_staging`
removes every file whose unit is not in the current plan (a removed, renamed, changed or shrunk input,
a half-written file of a killed run), and a tile is rebuilt exactly when the set of files that feed it
changes. A unit that fails removes what it had written, and a unit that is redone first removes its
previous output.

Top: pure helpers (arrays in, arrays out). Bottom: the stage functions the flow's tasks call.
"""

from __future__ import annotations

import contextlib
import logging
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from storage.atomic import file_fingerprint
from storage.columns import RUN_SUFFIX, write_run
from storage.errors import InputError
from storage.frame import CampusFrame
from storage.grid import PatchGrid
from storage.inputs import VERTEX_INDEX_BITS, InputFile
from storage.manifest import combine_fingerprints
from storage.mesh_io import MeshData, read_mesh
from storage.pointcloud_io import PointChunk, iter_points, iter_points_range
from storage.workdir import WorkDir
from tasks.config import CampusConfig
from tasks.partition.kernels import FACE_VERTEX_COLUMNS, partition_cells
from tasks.scan.stage import face_normals
from tasks.geometry.tiling import group_by_tile

log = logging.getLogger("ms3d.ingest")

LAS_SUFFIXES = (".las", ".laz")


@dataclass(frozen=True)
class IngestUnit:
    """One unit of ingest (JSON-able). start/stop: point range of a LAS/LAZ file (0, 0 otherwise)."""

    key: str
    source: int
    path: str
    kind: str  # "points" | "mesh"
    fingerprint: str
    start: int = 0
    stop: int = 0

    def to_json(self) -> dict:
        return asdict(self)


# ----------------------------------------------------------------------------------- pure helpers


def weld_vertex_index(vertices: np.ndarray) -> np.ndarray:
    """For each vertex, the lowest index of a vertex at exactly the same position.

    vertices: (n, 3) float64 -> (n,) int64. Seam-split vertices (glTF, PLY) get one id, so faces that
    share an edge share its vertex ids.

    >>> weld_vertex_index(np.array([[0., 0, 0], [1, 0, 0], [0, 0, 0]])).tolist()
    [0, 1, 0]
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    if len(v) == 0:
        return np.zeros(0, np.int64)
    rows = v.view(np.dtype((np.void, v.dtype.itemsize * 3))).ravel()
    _, first, inverse = np.unique(rows, return_index=True, return_inverse=True)
    return first.astype(np.int64)[inverse.ravel()]


def vertex_ids(source: int, faces: np.ndarray, canonical: np.ndarray) -> np.ndarray:
    """Campus-unique vertex ids ``source << 32 | canonical vertex index``. faces: (m, 3) -> (m, 3) int64."""
    if len(canonical) and canonical.max() >= (1 << VERTEX_INDEX_BITS):
        raise ValueError(f"a mesh file with more than 2**{VERTEX_INDEX_BITS} vertices")
    return (np.int64(source) << VERTEX_INDEX_BITS) | canonical[faces]


def point_columns(chunk: PointChunk, local: np.ndarray, source: int) -> dict[str, np.ndarray]:
    """Staging/patch-store point columns from a chunk and its campus-local float32 xyz (n, 3)."""
    n = len(local)
    rgb = chunk.rgb if chunk.rgb is not None else np.zeros((n, 3), np.uint16, order="F")
    u16 = lambda a: a.astype(np.uint16, copy=False)  # noqa: E731 - columns of an F-ordered (n, 3): no copy
    return {
        "x": local[:, 0], "y": local[:, 1], "z": local[:, 2],
        "intensity": chunk.intensity if chunk.intensity is not None else np.zeros(n, np.uint16),
        "gps_time": chunk.gps_time if chunk.gps_time is not None else np.zeros(n, np.float64),
        "red": u16(rgb[:, 0]), "green": u16(rgb[:, 1]), "blue": u16(rgb[:, 2]),
        "classification": chunk.classification if chunk.classification is not None else np.zeros(n, np.uint8),
        "source": np.full(n, source, np.uint32),
    }  # fmt: skip


def face_columns(mesh: MeshData, tri_local: np.ndarray, vids: np.ndarray, normals: np.ndarray,
                 source: int) -> dict[str, np.ndarray]:
    """Staging/patch-store face columns.

    tri_local: (m, 3, 3) float32 campus-local metres; vids: (m, 3) int64 vertex ids; normals: (m, 3) unit.
    """
    m = len(tri_local)
    cols = {f"{a}{v}": tri_local[:, v, ai] for v in range(3) for ai, a in enumerate("xyz")}
    cols = {k: cols[k] for k in FACE_VERTEX_COLUMNS}
    for v in range(3):
        cols[f"vid{v}"] = vids[:, v]
    cols["nx"], cols["ny"], cols["nz"] = (normals[:, i].astype(np.float32) for i in range(3))
    uv = mesh.uv if mesh.uv is not None else np.full((m, 3, 2), np.nan, np.float32)
    for v in range(3):
        cols[f"u{v}"] = uv[:, v, 0].astype(np.float32)
        cols[f"v{v}"] = uv[:, v, 1].astype(np.float32)
    tex = mesh.face_texture if mesh.face_texture is not None else np.full(m, -1, np.int16)
    cols["texture"] = tex.astype(np.int16)
    fc = mesh.face_colors if mesh.face_colors is not None else np.full((m, 3), 200, np.uint8)
    cols["red"], cols["green"], cols["blue"] = (fc[:, i].astype(np.uint8) for i in range(3))
    cols["src_face"] = np.arange(m, dtype=np.int64)
    cols["source"] = np.full(m, source, np.uint32)
    return cols


def to_campus(world: np.ndarray, frame: CampusFrame, matrix: np.ndarray | None, source: str) -> np.ndarray:
    """world (n, 3) float64 -> campus-local (n, 3) float64 (column-major), applying the registration when given.

    Patch cells are computed from this float64 result (``origin + local``, i.e. world coordinates), not
    from the float32 values stored, so a place keeps its patch whatever the origin; the cast to float32
    moves a point by at most ~0.1 mm within the checked reach. NaN/inf and points too far from the origin
    for float32 raise InputError naming ``source``.
    """
    from storage.frame import MAX_LOCAL_EXTENT_M

    world = np.asarray(world)
    n = len(world)
    d = [np.subtract(world[:, a], frame.origin_array[a], dtype=np.float64) for a in range(3)]  # contiguous columns
    if matrix is None:
        local = np.empty((n, 3), np.float64, order="F")
        for a in range(3):
            local[:, a] = d[a]
    else:  # per output axis, in place on contiguous columns: ~3x a (n, 3) @ (3, 3) on C-ordered rows
        m = np.asarray(matrix, np.float64)
        local = np.empty((n, 3), np.float64, order="F")
        for a in range(3):
            col = local[:, a]
            np.multiply(d[0], m[a, 0], out=col)
            col += m[a, 1] * d[1]
            col += m[a, 2] * d[2]
            col += m[a, 3]
    if n:
        lo = np.array([local[:, a].min() for a in range(3)])  # NaN propagates into both
        hi = np.array([local[:, a].max() for a in range(3)])
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            bad = int((~np.isfinite(local).all(axis=1)).sum())
            raise InputError(source, f"{bad} coordinates are NaN or infinite")
        reach = float(max(np.abs(lo[:2]).max(), np.abs(hi[:2]).max()))
        if reach > MAX_LOCAL_EXTENT_M * 5:
            raise InputError(source, f"coordinates lie {reach:,.0f} m from the campus origin {frame.origin}: wrong "
                                     "CRS, units or a mismatched extent (inputs must overlap the campus)")
    return local


# ----------------------------------------------------------------------------------- planning


def unit_key(kind: str, source: int, fp: str, part: int) -> str:
    return f"{'m' if kind == 'mesh' else 'p'}{source:08x}-{fp[:8]}-{part:05d}"


def plan_units(records: list[InputFile], chunk_points: int) -> list[IngestUnit]:
    """Ingest units of the readable inputs: whole mesh files, ranges of ``chunk_points`` per LAS/LAZ
    file, whole files of other point formats."""
    units = []
    for r in sorted(records, key=lambda r: (r.kind, r.source)):
        if r.error:
            continue
        if r.kind == "mesh":
            units.append(IngestUnit(unit_key("mesh", r.source, r.fingerprint, 0), r.source, r.path, "mesh", r.fingerprint))
        elif Path(r.path).suffix.lower() in LAS_SUFFIXES:
            for c, a in enumerate(range(0, r.count, chunk_points)):
                units.append(IngestUnit(unit_key("points", r.source, r.fingerprint, c), r.source, r.path, "points",
                                        r.fingerprint, a, min(a + chunk_points, r.count)))
        else:
            units.append(IngestUnit(unit_key("points", r.source, r.fingerprint, 0), r.source, r.path, "points",
                                    r.fingerprint, 0, r.count))
    return units


def tiles_hint(rec: InputFile, frame: CampusFrame, matrix: np.ndarray, grid: PatchGrid) -> list[str]:
    """Tile keys the file's bounds cover (empty when its extent is unknown). Point bounds are mapped by
    the registration first."""
    from tasks.geometry.tiling import transform_bounds

    if not rec.bounded:
        return []
    lo, hi = np.asarray(rec.lo, np.float64), np.asarray(rec.hi, np.float64)
    if rec.kind == "points":
        o = frame.origin_array
        lo, hi = transform_bounds(matrix, lo - o, hi - o)
        lo, hi = lo + o, hi + o
    return [f"{i}_{j}" for i, j in grid.tiles_for_bounds(lo, hi, margin_m=1.0).tolist()]


def prune_staging(wd: WorkDir, keys: set[str]) -> int:
    """Remove staging files of units not in ``keys`` (and temporary files); returns how many."""
    root = wd.root / "staging"
    removed = 0
    if not root.exists():
        return 0
    for d in root.iterdir():
        if not d.is_dir():
            continue
        for f in d.iterdir():
            if f.name.startswith(".") or not f.name.endswith(RUN_SUFFIX) or f.name.rsplit("-", 1)[0] not in keys:
                f.unlink(missing_ok=True)
                removed += 1
        with contextlib.suppress(OSError):
            d.rmdir()  # only when empty
    return removed


def staged_files(wd: WorkDir, tile_key: str) -> list[Path]:
    """The complete staging runs of a tile (temporary names excluded), sorted by name."""
    d = wd.root / "staging" / tile_key
    return sorted(p for p in d.glob(f"*{RUN_SUFFIX}") if not p.name.startswith(".")) if d.exists() else []


# ----------------------------------------------------------------------------------- stage: ingest


def _remove(wd: WorkDir, rel: list[str]) -> None:
    for r in rel:
        (wd.root / r).unlink(missing_ok=True)


def _route_points(unit: IngestUnit, cfg: CampusConfig, frame: CampusFrame, matrix: np.ndarray,
                  wd: WorkDir, outputs: list[str], tiles: dict) -> None:
    grid = cfg.grid()
    if Path(unit.path).suffix.lower() in LAS_SUFFIXES:
        chunks = iter_points_range(unit.path, unit.start, unit.stop, cfg.tiling.chunk_points, cfg.inputs.units_scale)
    else:
        chunks = iter_points(unit.path, cfg.tiling.chunk_points, cfg.inputs.units_scale)
    n = 0
    for k, chunk in enumerate(chunks):
        local64 = to_campus(chunk.xyz, frame, matrix, unit.path)
        cells = grid.cells_local(local64, frame.origin)
        cols = point_columns(chunk, local64.astype(np.float32), unit.source)
        del local64
        cols["patch"] = grid.pack(cells)
        _write_runs(wd, f"{unit.key}-{k:03d}", cols, cells, grid, None, outputs, tiles)
        n += len(chunk)
    if n == 0:
        raise InputError(unit.path, f"no points in range [{unit.start}, {unit.stop})")


def _route_mesh(unit: IngestUnit, cfg: CampusConfig, frame: CampusFrame, wd: WorkDir,
                outputs: list[str], tiles: dict) -> dict:
    grid = cfg.grid()
    mesh = read_mesh(unit.path, offset=cfg.inputs.mesh_offset, units_scale=cfg.inputs.units_scale)
    vids = vertex_ids(unit.source, mesh.faces, weld_vertex_index(mesh.vertices))
    normals = face_normals(mesh.vertices, mesh.faces)
    local64 = to_campus(mesh.vertices, frame, None, unit.path)
    vkeys = grid.pack(grid.cells_local(local64, frame.origin))  # Algorithm 1 step 3: patch of each vertex
    tri64 = local64[mesh.faces]  # (m, 3, 3) float64
    cells = grid.face_cells([tri64[:, v, a] for v in range(3) for a in range(3)], frame.origin)
    cols = face_columns(mesh, tri64.astype(np.float32), vids, normals, unit.source)
    cols["patch"] = grid.pack(cells)
    for v in range(3):
        cols[f"vp{v}"] = vkeys[mesh.faces[:, v]]
    meta = {"textures": mesh.textures, "source": unit.path,
            "n_degenerate_dropped": mesh.n_degenerate_dropped, "n_duplicate_dropped": mesh.n_duplicate_dropped}
    _write_runs(wd, f"{unit.key}-000", cols, cells, grid, meta, outputs, tiles)
    return {"n_degenerate_dropped": mesh.n_degenerate_dropped, "n_duplicate_dropped": mesh.n_duplicate_dropped,
            "n_nonmanifold_edges": mesh.n_nonmanifold_edges}


def _write_runs(wd: WorkDir, name: str, cols: dict, cells: np.ndarray, grid: PatchGrid, meta: dict | None,
                outputs: list[str], tiles: dict) -> None:
    """Route rows to their tiles as sorted runs (``staging/{tile}/{name}.parquet``, sorted by patch, stable),
    which the partition stage merges without sorting a whole tile in memory."""
    order = partition_cells(cells).order  # stable by patch key
    for tile, idx in group_by_tile(grid.tile_of_cells(cells)[order]):  # stable: each tile stays key-sorted
        rows = order[idx]
        out = wd.staging_dir(tile) / f"{name}{RUN_SUFFIX}"
        write_run(out, {c: v[rows] for c, v in cols.items()}, meta)
        outputs.append(str(out.relative_to(wd.root)))
        tiles[tile.key] = tiles.get(tile.key, 0) + len(rows)


def ingest_fingerprint(unit: IngestUnit, frame: CampusFrame, matrix: np.ndarray | None) -> str:
    parts = [unit.key, unit.fingerprint, f"{unit.start}:{unit.stop}", str(frame.to_json())]
    if unit.kind == "points":
        parts.append(np.asarray(matrix, np.float64).tobytes().hex())
    return combine_fingerprints(parts)


def run_ingest_unit(unit: IngestUnit, cfg: CampusConfig, wd: WorkDir, frame: CampusFrame,
                    matrix: np.ndarray | None) -> dict:
    """Route one unit's points or faces to staging files per tile (skipped when done and unchanged).

    matrix: (4, 4) registration for point units (None for meshes, which define the frame).
    """
    from tasks.units import Done, run_unit

    def work() -> Done:
        for old in (wd.root / "staging").glob(f"*/{unit.key}-*{RUN_SUFFIX}"):
            old.unlink(missing_ok=True)  # a redone unit starts clean
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


def staging_fingerprint(parts: list[Path]) -> list[str]:
    return [f"{p.name}:{file_fingerprint(p)}" for p in parts]
