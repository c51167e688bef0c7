"""Ingest: scan the inputs, pick the campus frame, and route points/faces to their tiles.

Top: pure helpers (arrays in, arrays out). Bottom: the stage functions the flow's tasks call, which take
ids, paths and the config, read and write the work dir atomically, and return small summaries.

Routing writes *staging* files, ``staging/{tile}/points-{unit}-{k}.parquet`` and
``staging/{tile}/faces-{unit}.parquet``, which the partition stage of that tile reads. An ingest unit
is a range of points of one cloud file or one mesh file; a unit's ``tiles_hint`` (the tiles its
header bounds cover) says which tiles must fail when the unit's input is bad.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from storage.atomic import file_fingerprint
from storage.columns import write_columns
from storage.errors import InputError
from storage.frame import CampusFrame
from storage.manifest import ManifestRecord, combine_fingerprints, is_done, params_hash, write_record
from storage.mesh_io import MeshData, mesh_files, read_mesh
from storage.pointcloud_io import PointChunk, iter_points, iter_points_range, read_header
from storage.workdir import WorkDir
from tasks.config import CampusConfig
from tasks.partition import tile_of_faces, tile_of_points
from tasks.tiling import group_by_tile, tiles_for_bounds, transform_bounds

log = logging.getLogger("ms3d.ingest")

POINT_SUFFIXES = {".las", ".laz", ".ply", ".pcd", ".xyz", ".txt", ".pts"}
MESH_SUFFIXES = {".obj", ".ply", ".glb", ".gltf", ".off", ".stl"}


@dataclass
class InputFile:
    """One input file as scanned by the register stage (JSON-able, stored in campus.json)."""

    index: int
    path: str
    kind: str  # "points" | "mesh"
    fingerprint: str
    count: int = 0
    lo: list[float] = field(default_factory=list)  # world bounds (mesh: after offset/scale)
    hi: list[float] = field(default_factory=list)
    crs: str | None = None
    error: str = ""


@dataclass(frozen=True)
class IngestUnit:
    key: str
    file_index: int
    path: str
    kind: str
    start: int = 0
    stop: int = 0


# ----------------------------------------------------------------------------------- pure helpers


def point_columns(chunk: PointChunk, local: np.ndarray, source: int) -> dict[str, np.ndarray]:
    """Staging/patch-store point columns from a chunk and its campus-local float32 xyz (n, 3)."""
    n = len(local)
    rgb = chunk.rgb if chunk.rgb is not None else np.zeros((n, 3), np.uint16)
    return {
        "x": local[:, 0], "y": local[:, 1], "z": local[:, 2],
        "intensity": chunk.intensity if chunk.intensity is not None else np.zeros(n, np.uint16),
        "gps_time": chunk.gps_time if chunk.gps_time is not None else np.zeros(n, np.float64),
        "red": rgb[:, 0].astype(np.uint16), "green": rgb[:, 1].astype(np.uint16), "blue": rgb[:, 2].astype(np.uint16),
        "classification": chunk.classification if chunk.classification is not None else np.zeros(n, np.uint8),
        "source": np.full(n, source, np.uint16),
    }  # fmt: skip


def face_columns(mesh: MeshData, tri_local: np.ndarray, source: int) -> dict[str, np.ndarray]:
    """Staging/patch-store face columns: tri_local (m, 3, 3) float32 campus-local metres."""
    m = len(tri_local)
    cols = {f"{a}{v}": tri_local[:, v, ai] for v in range(3) for ai, a in enumerate("xyz")}
    cols = {k: cols[k] for k in ("x0", "y0", "z0", "x1", "y1", "z1", "x2", "y2", "z2")}
    uv = mesh.uv if mesh.uv is not None else np.full((m, 3, 2), np.nan, np.float32)
    for v in range(3):
        cols[f"u{v}"] = uv[:, v, 0].astype(np.float32)
        cols[f"v{v}"] = uv[:, v, 1].astype(np.float32)
    tex = mesh.face_texture if mesh.face_texture is not None else np.full(m, -1, np.int16)
    cols["texture"] = tex.astype(np.int16)
    fc = mesh.face_colors if mesh.face_colors is not None else np.full((m, 3), 200, np.uint8)
    cols["red"], cols["green"], cols["blue"] = (fc[:, i].astype(np.uint8) for i in range(3))
    cols["src_face"] = np.arange(m, dtype=np.int64)
    cols["source"] = np.full(m, source, np.uint16)
    return cols


def to_campus(world: np.ndarray, frame: CampusFrame, matrix: np.ndarray | None, source: str) -> np.ndarray:
    """world (n, 3) float64 -> campus-local (n, 3) float32, applying the registration when given."""
    local = np.asarray(world, np.float64) - frame.origin_array
    if not np.isfinite(local).all():
        raise InputError(source, f"{int((~np.isfinite(local).all(axis=1)).sum())} coordinates are NaN or infinite")
    if matrix is not None:
        m = np.asarray(matrix, np.float64)
        local = local @ m[:3, :3].T + m[:3, 3]
    return frame.to_local(local + frame.origin_array, source)


# ----------------------------------------------------------------------------------- input scan


def expand_inputs(cfg: CampusConfig) -> tuple[list[Path], list[Path]]:
    """The mesh and point files named by the config (folders expanded, sorted)."""
    meshes: list[Path] = []
    for p in map(Path, cfg.inputs.mesh):
        if p.is_dir():
            meshes += mesh_files(p)
        elif p.exists():
            meshes.append(p)
        else:
            raise InputError(p, "mesh input does not exist")
    points: list[Path] = []
    for p in map(Path, cfg.inputs.points):
        if p.is_dir():
            points += sorted(q for q in p.rglob("*") if q.suffix.lower() in POINT_SUFFIXES)
        elif p.exists():
            points.append(p)
        else:
            raise InputError(p, "point-cloud input does not exist")
    if not meshes:
        raise InputError(None, "no mesh input: set inputs.mesh in the config")
    if not points:
        raise InputError(None, "no point-cloud input: set inputs.points in the config")
    return meshes, points


def _salvage_mesh_bounds(path: Path, cfg: CampusConfig) -> tuple[list, list]:
    """Bounds of the finite vertices of a mesh that failed validation (to know which tiles it hits)."""
    try:
        import trimesh

        m = trimesh.load(path, process=False, force="mesh")
        v = np.asarray(m.vertices, np.float64)
        v = v[np.isfinite(v).all(axis=1)] * cfg.inputs.units_scale + np.asarray(cfg.inputs.mesh_offset)
        if len(v):
            return v.min(axis=0).tolist(), v.max(axis=0).tolist()
    except Exception:  # noqa: BLE001 - best effort; an unknown extent fails every tile
        pass
    return [], []


def scan_mesh(index: int, path: Path, cfg: CampusConfig) -> tuple[InputFile, np.ndarray | None]:
    """Read one mesh file; returns its InputFile record and its world vertices (None on error)."""
    rec = InputFile(index=index, path=str(path), kind="mesh", fingerprint=file_fingerprint(path))
    try:
        mesh = read_mesh(path, offset=cfg.inputs.mesh_offset, units_scale=cfg.inputs.units_scale)
    except InputError as e:
        rec.error = str(e)
        rec.lo, rec.hi = _salvage_mesh_bounds(path, cfg)
        return rec, None
    used = np.unique(mesh.faces)
    v = mesh.vertices[used]
    rec.count = int(mesh.n_faces)
    rec.lo, rec.hi = v.min(axis=0).tolist(), v.max(axis=0).tolist()
    return rec, v


def scan_points(index: int, path: Path, cfg: CampusConfig) -> InputFile:
    rec = InputFile(index=index, path=str(path), kind="points", fingerprint=file_fingerprint(path))
    try:
        info = read_header(path)
        s = cfg.inputs.units_scale
        rec.count = int(info.point_count)
        rec.lo, rec.hi = (info.bounds[0] * s).tolist(), (info.bounds[1] * s).tolist()
        rec.crs = info.crs
    except InputError as e:
        rec.error = str(e)
        rec.lo, rec.hi = _salvage_cloud_bounds(path, cfg)
    return rec


def _salvage_cloud_bounds(path: Path, cfg: CampusConfig) -> tuple[list, list]:
    """The header bounds of a LAS/LAZ file whose points are unreadable (to know which tiles it hits)."""
    try:
        import laspy

        with laspy.open(path) as f:
            lo, hi = np.asarray(f.header.mins, float), np.asarray(f.header.maxs, float)
        if np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all():
            return (lo * cfg.inputs.units_scale).tolist(), (hi * cfg.inputs.units_scale).tolist()
    except Exception:  # noqa: BLE001 - best effort; an unknown extent fails every tile
        pass
    return [], []


def sample_points_for_registration(rec: InputFile, n_target: int, cfg: CampusConfig, n_ranges: int = 16) -> np.ndarray:
    """About n_target world points spread over a cloud file: n_ranges short ranges (LAS/LAZ) or a
    strided pass (other formats). Errors inside the file end the sample early (logged)."""
    path = Path(rec.path)
    out = []
    try:
        if path.suffix.lower() in (".las", ".laz") and rec.count > n_target:
            per = max(n_target // n_ranges, 1)
            starts = np.linspace(0, max(rec.count - per, 0), n_ranges).astype(np.int64)
            for a in starts:
                for ch in iter_points_range(path, int(a), int(a) + per, per, cfg.inputs.units_scale):
                    out.append(ch.xyz)
        else:
            stride = max(rec.count // max(n_target, 1), 1)
            for ch in iter_points(path, cfg.tiling.chunk_points, cfg.inputs.units_scale):
                out.append(ch.xyz[::stride])
    except InputError as e:
        log.warning("registration sample of %s ended early: %s", path, e)
    xyz = np.concatenate(out) if out else np.zeros((0, 3))
    return xyz[np.isfinite(xyz).all(axis=1)]


def plan_units(inputs: list[InputFile], cfg: CampusConfig) -> list[IngestUnit]:
    """Ingest units: ranges of ``chunk_points`` points per cloud file (LAS/LAZ), whole files otherwise."""
    units = []
    for rec in inputs:
        if rec.kind == "mesh":
            units.append(IngestUnit(f"m{rec.index:03d}", rec.index, rec.path, "mesh"))
        elif Path(rec.path).suffix.lower() in (".las", ".laz") and rec.count > 0:
            n = cfg.tiling.chunk_points
            for c, a in enumerate(range(0, rec.count, n)):
                units.append(IngestUnit(f"p{rec.index:03d}-{c:05d}", rec.index, rec.path, "points", a, min(a + n, rec.count)))
        else:
            units.append(IngestUnit(f"p{rec.index:03d}-00000", rec.index, rec.path, "points", 0, rec.count))
    return units


def tiles_hint(rec: InputFile, frame: CampusFrame, matrix: np.ndarray, tile_size_m: float) -> list[str]:
    """Tile keys the file's bounds cover in the campus frame (empty when the extent is unknown)."""
    if not rec.lo:
        return []
    lo = np.asarray(rec.lo) - frame.origin_array
    hi = np.asarray(rec.hi) - frame.origin_array
    if rec.kind == "points":
        lo, hi = transform_bounds(matrix, lo, hi)
    return [t.key for t in tiles_for_bounds(lo, hi, tile_size_m, margin_m=1.0)]


# ----------------------------------------------------------------------------------- stage: ingest


def ingest_params(cfg: CampusConfig, campus: dict) -> dict:
    return cfg.stage_params("ingest") | {
        "frame": campus["frame"], "matrix": campus["registration"]["matrix"],
        "mesh_offset": list(cfg.inputs.mesh_offset), "units_scale": cfg.inputs.units_scale,
    }


def run_ingest_unit(unit: IngestUnit, cfg: CampusConfig, wd: WorkDir, campus: dict) -> dict:
    """Route one unit's points or faces to staging files per tile. Skips when done and unchanged."""
    frame = CampusFrame.from_json(campus["frame"])
    matrix = np.asarray(campus["registration"]["matrix"], np.float64)
    rec_in = campus["inputs"][unit.file_index]
    fp = combine_fingerprints([rec_in["fingerprint"], f"{unit.start}:{unit.stop}"])
    ph = params_hash(ingest_params(cfg, campus))
    done = is_done(wd, "ingest", unit.key, fp, ph)
    if done is not None:
        return done.summary | {"skipped": True}
    t0 = time.perf_counter()
    for old in (wd.root / "staging").glob(f"*/*-{unit.key}*.parquet"):
        old.unlink()  # a changed unit must not leave stale rows behind
    outputs: list[str] = []
    tiles: dict[str, int] = {}
    try:
        if rec_in.get("error"):
            raise InputError(unit.path, rec_in["error"].split(": ", 1)[-1])
        if unit.kind == "points":
            chunks = iter_points_range(unit.path, unit.start, unit.stop, cfg.tiling.chunk_points, cfg.inputs.units_scale) \
                if Path(unit.path).suffix.lower() in (".las", ".laz") else iter_points(unit.path, cfg.tiling.chunk_points, cfg.inputs.units_scale)
            n = 0
            for k, chunk in enumerate(chunks):
                local = to_campus(chunk.xyz, frame, matrix, unit.path)
                cols = point_columns(chunk, local, unit.file_index)
                tij = tile_of_points(local, cfg.partition.patch_size_m, cfg.tiling.tile_size_m)
                for tile, idx in group_by_tile(tij):
                    out = wd.staging_dir(tile) / f"points-{unit.key}-{k:04d}.parquet"
                    write_columns(out, {c: v[idx] for c, v in cols.items()})
                    outputs.append(str(out.relative_to(wd.root)))
                    tiles[tile.key] = tiles.get(tile.key, 0) + len(idx)
                n += len(chunk)
            if n == 0:
                raise InputError(unit.path, f"no points in range [{unit.start}, {unit.stop})")
        else:
            mesh = read_mesh(unit.path, offset=cfg.inputs.mesh_offset, units_scale=cfg.inputs.units_scale)
            tri_world = mesh.vertices[mesh.faces]  # (m, 3, 3) float64
            tri = to_campus(tri_world.reshape(-1, 3), frame, None, unit.path).reshape(-1, 3, 3)
            cols = face_columns(mesh, tri, unit.file_index)
            meta = {"textures": mesh.textures, "source": unit.path,
                    "n_degenerate_dropped": mesh.n_degenerate_dropped, "n_duplicate_dropped": mesh.n_duplicate_dropped}
            for tile, idx in group_by_tile(tile_of_faces(tri, cfg.partition.patch_size_m, cfg.tiling.tile_size_m)):
                out = wd.staging_dir(tile) / f"faces-{unit.key}.parquet"
                write_columns(out, {c: v[idx] for c, v in cols.items()}, meta)
                outputs.append(str(out.relative_to(wd.root)))
                tiles[tile.key] = tiles.get(tile.key, 0) + len(idx)
    except InputError as e:
        write_record(wd, ManifestRecord("ingest", unit.key, "failed", fp, ph, error=str(e),
                                        seconds=time.perf_counter() - t0))
        raise
    summary = {"unit": unit.key, "kind": unit.kind, "rows": int(sum(tiles.values())), "tiles": tiles}
    write_record(wd, ManifestRecord("ingest", unit.key, "done", fp, ph, seconds=time.perf_counter() - t0,
                                    outputs=outputs, summary=summary))
    return summary


def unit_to_json(u: IngestUnit) -> dict:
    return asdict(u)


# ----------------------------------------------------------------------------------- stage: register


def choose_frame(mesh_recs: list[InputFile], point_recs: list[InputFile], crs: str | None) -> CampusFrame:
    """The campus origin: the minimum x/y corner of the mesh extent snapped to 100 m, z = 0."""
    los = [r.lo for r in mesh_recs if r.lo] or [r.lo for r in point_recs if r.lo]
    if not los:
        raise InputError(None, "no readable input: every mesh and point-cloud file failed (see errors above)")
    return CampusFrame.around(np.asarray(los, np.float64), crs=crs)


def resolve_crs(cfg: CampusConfig, point_recs: list[InputFile]) -> str | None:
    """The config CRS, else the CRS of the LAS headers; disagreement is an input error."""
    found = {r.crs for r in point_recs if r.crs}
    if cfg.inputs.crs:
        for r in point_recs:
            if r.crs and r.crs != cfg.inputs.crs:
                raise InputError(r.path, f"CRS {r.crs} in the file disagrees with the configured {cfg.inputs.crs}")
        return cfg.inputs.crs
    if len(found) > 1:
        raise InputError(None, f"point clouds carry different CRSs {sorted(found)}: set inputs.crs or reproject")
    return found.pop() if found else None


def register_params(cfg: CampusConfig) -> dict:
    return cfg.stage_params("register")


def run_register(cfg: CampusConfig, wd: WorkDir) -> dict:
    """Scan the inputs, choose the campus frame, register the MLS cloud to the mesh, write campus.json.

    Skipped when campus.json exists with the same input fingerprints and registration parameters.
    """
    from storage.workdir import read_campus, write_campus

    meshes, points = expand_inputs(cfg)
    fps = [file_fingerprint(p) for p in meshes + points]
    fp = combine_fingerprints(fps + [str(p) for p in meshes + points])
    ph = params_hash(register_params(cfg))
    done = is_done(wd, "register", "campus", fp, ph)
    if done is not None and wd.campus_json.exists():
        return read_campus(wd)
    t0 = time.perf_counter()
    mesh_recs, mesh_vertices = [], []
    for i, p in enumerate(meshes):
        rec, v = scan_mesh(i, p, cfg)
        mesh_recs.append(rec)
        if v is not None:
            mesh_vertices.append(v)
    point_recs = [scan_points(len(meshes) + i, p, cfg) for i, p in enumerate(points)]
    for r in mesh_recs + point_recs:
        if r.error:
            log.warning("input problem: %s", r.error)
    crs = resolve_crs(cfg, point_recs)
    frame = choose_frame(mesh_recs, point_recs, crs)
    if not mesh_vertices:
        raise InputError(None, "no readable mesh: " + "; ".join(r.error for r in mesh_recs))
    target = np.concatenate(mesh_vertices) - frame.origin_array
    n_each = max(cfg.registration.max_points * 4 // max(len(point_recs), 1), 10_000)
    source = [sample_points_for_registration(r, n_each, cfg) for r in point_recs if not r.error]
    source = np.concatenate(source) - frame.origin_array if source else np.zeros((0, 3))
    if len(source) < 100:
        raise InputError(None, "no readable MLS points to register: " + "; ".join(r.error for r in point_recs if r.error))
    far = np.abs(np.median(source[:, :2], axis=0) - np.median(target[:, :2], axis=0))
    if (far > 5 * 2000).any():
        raise InputError(points[0], f"the MLS cloud lies {far.max():,.0f} m from the mesh: wrong CRS, units or mesh offset")
    if cfg.registration.enabled:
        from tasks.register import register_clouds

        result = register_clouds(source, target, cfg.registration)
        registration = result.to_json()
    else:
        from tasks.register import check_coregistered

        ok, med = check_coregistered(source, target)
        if not ok:
            log.warning("registration is switched off but the MLS points lie %.3f m (median) from the mesh "
                        "vertices: the inputs do not look co-registered", med)
        registration = {"matrix": np.eye(4).tolist(), "scale": 1.0, "method": "identity (registration disabled)",
                        "check_median_distance_m": med, "check_ok": bool(ok)}
    registration["seconds"] = time.perf_counter() - t0
    inputs = sorted(mesh_recs + point_recs, key=lambda r: r.index)
    write_campus(wd, frame, registration, cfg.model_dump(mode="json"),
                 extra={"inputs": [asdict(r) for r in inputs], "name": cfg.name})
    write_record(wd, ManifestRecord("register", "campus", "done", fp, ph, seconds=time.perf_counter() - t0,
                                    outputs=["campus.json"], summary={k: registration.get(k) for k in ("scale", "fitness", "inlier_rmse_m", "method")}))
    return read_campus(wd)
