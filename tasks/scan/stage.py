"""Scan the inputs once per content: bounds, counts, CRS, errors, and the mesh surface samples that
registration aligns to; then choose the campus frame.

One scan unit per input file, keyed by the file's stable source id and skipped while its content
fingerprint is unchanged, so a nightly run over a thousand unchanged ContextCapture tiles reads none
of them. A mesh is read once here: its world bounds and face count go to the record, and area-weighted
samples of its surface (``registration.target_spacing_m``) go to ``scan/{source}.npz``, so registration
never re-reads a mesh and its target density does not depend on the tessellation (a coarse LoD2-like
model of a few hundred triangles is sampled as densely as a 10 cm MVS mesh).

A file that cannot be read is still scanned: its record carries the error and, when the file says
where it lies (a LAS header, the finite vertices of a broken mesh), its bounds, so that exactly the
tiles it covers are blocked. A file whose bounds are unknown blocks no tile and makes the campus
incomplete.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path
from storage.errors import InputError
from storage.frame import CampusFrame
from storage.inputs import InputFile, fingerprint
from storage.mesh_io import read_mesh
from storage.pointcloud_io import read_header
from storage.workdir import WorkDir
from tasks.config import CampusConfig
from tasks.units import Done, run_unit

log = logging.getLogger("ms3d.scan")

ORIGIN_SNAP_M = 1000.0  # the origin moves only when the campus crosses a kilometre line


# ----------------------------------------------------------------------------------- pure helpers


def face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit normals (right hand on corners 0 -> 1 -> 2). vertices: (n, 3) float64; faces: (m, 3) int
    -> (m, 3) float64 (zero for a degenerate face)."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


MAX_SAMPLES_PER_FILE = 20_000_000  # registration crops and caps the samples near the MLS anyway


def surface_samples(vertices: np.ndarray, faces: np.ndarray, spacing_m: float, seed: int = 0):
    """Area-weighted samples of a triangle surface with their face normals
    (:func:`tasks.register.align.mesh_registration_target`). vertices: (n, 3) float64 metres; faces: (m, 3)
    int. Returns xyz (k, 3) float64 and normals (k, 3) float32."""
    from tasks.register.align import mesh_registration_target

    xyz, nrm = mesh_registration_target(vertices, faces, spacing_m, MAX_SAMPLES_PER_FILE, seed)
    return xyz, nrm.astype(np.float32)


def choose_origin(records: list[InputFile], fixed=None) -> tuple[float, float, float]:
    """The campus origin: ``fixed`` (config), else the minimum x/y corner of every known input extent
    snapped down to :data:`ORIGIN_SNAP_M`, z = 0. A function of the inputs only, so a clean run and a
    resumed run agree."""
    if fixed is not None:
        return tuple(float(v) for v in fixed)
    los = [r.lo for r in records if r.bounded]
    if not los:
        raise InputError(None, "no input could be read (every mesh and point-cloud file failed; see above)")
    lo = np.min(np.asarray(los, np.float64)[:, :2], axis=0)
    o = np.floor(lo / ORIGIN_SNAP_M) * ORIGIN_SNAP_M
    return float(o[0]), float(o[1]), 0.0


def resolve_crs(configured: str | None, point_recs: list[InputFile]) -> str | None:
    """The configured CRS, else the one the LAS headers agree on; disagreement is an input error."""
    found = {r.crs for r in point_recs if r.crs and not r.error}
    if configured:
        for r in point_recs:
            if r.crs and r.crs != configured and not r.error:
                raise InputError(r.path, f"CRS {r.crs} in the file disagrees with the configured {configured}: "
                                         "reproject the file or fix inputs.crs")
        return configured
    if len(found) > 1:
        raise InputError(None, f"point clouds carry different CRSs {sorted(found)}: set inputs.crs or reproject")
    return found.pop() if found else None


def check_crs_is_projected(crs: str | None) -> None:
    """A geographic CRS (degrees) cannot be partitioned in metres: say so before anything is read."""
    if not crs:
        return
    try:
        from pyproj import CRS

        c = CRS.from_user_input(crs)
    except Exception as e:  # noqa: BLE001 - pyproj raises several types for a bad string
        raise InputError(None, f"unknown CRS {crs!r} ({e}); give e.g. inputs.crs: EPSG:32650") from None
    horizontal = c.sub_crs_list[0] if c.is_compound and c.sub_crs_list else c
    if horizontal.is_geographic:
        raise InputError(None, f"CRS {crs} is geographic (degrees): ms3d needs a projected CRS in metres "
                               "(e.g. the UTM zone of the campus); reproject the inputs")


def check_overlap(records: list[InputFile], margin_m: float = 50.0) -> None:
    """Raise InputError naming both extents when the point clouds and the meshes do not overlap at all."""
    def box(kind):
        rs = [r for r in records if r.kind == kind and r.bounded and not r.error]
        if not rs:
            return None
        lo = np.min([r.lo for r in rs], axis=0)
        hi = np.max([r.hi for r in rs], axis=0)
        return lo, hi

    pts, mesh = box("points"), box("mesh")
    if pts is None or mesh is None:
        return
    sep = np.maximum(pts[0][:2] - mesh[1][:2], mesh[0][:2] - pts[1][:2])
    if (sep > margin_m).any():
        fmt = lambda b: f"x {b[0][0]:,.0f}..{b[1][0]:,.0f}, y {b[0][1]:,.0f}..{b[1][1]:,.0f}"
        raise InputError(None, f"the point clouds ({fmt(pts)}) and the meshes ({fmt(mesh)}) do not overlap "
                               f"(they are {float(sep.max()):,.0f} m apart): wrong CRS or zone, units, or "
                               "inputs.mesh_offset")


# ----------------------------------------------------------------------------------- stage: scan


def _raw_vertices(path: Path) -> np.ndarray:
    """Vertex positions of a mesh file that failed validation: the ``v`` lines of an OBJ (whatever its
    faces say), else whatever trimesh can load. (n, 3) float64, possibly empty."""
    if path.suffix.lower() == ".obj":
        rows = []
        with open(path, errors="replace") as f:
            for line in f:  # the error path only: a Python loop is fine here
                if line.startswith("v "):
                    parts = line.split()[1:4]
                    try:
                        rows.append([float(p) for p in parts])
                    except ValueError:
                        continue
        return np.asarray(rows, np.float64).reshape(-1, 3)
    import trimesh

    return np.asarray(trimesh.load(path, process=False, force="mesh").vertices, np.float64)


def _salvage_mesh_bounds(path: Path, cfg: CampusConfig) -> tuple[list, list]:
    """Bounds of the finite vertices of a mesh that failed validation (to know which tiles it hits)."""
    try:
        v = _raw_vertices(path)
        v = v[np.isfinite(v).all(axis=1)] * cfg.inputs.units_scale + np.asarray(cfg.inputs.mesh_offset)
        if len(v):
            return v.min(axis=0).tolist(), v.max(axis=0).tolist()
    except Exception:  # noqa: BLE001 - best effort; unknown bounds block no tile
        pass
    return [], []


def _salvage_cloud_bounds(path: Path, cfg: CampusConfig) -> tuple[list, list]:
    """The header bounds of a LAS/LAZ file whose points are unreadable (to know which tiles it hits)."""
    try:
        import laspy

        with laspy.open(path) as f:
            lo, hi = np.asarray(f.header.mins, float), np.asarray(f.header.maxs, float)
        if np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all() and (hi > lo).any():
            return (lo * cfg.inputs.units_scale).tolist(), (hi * cfg.inputs.units_scale).tolist()
    except Exception:  # noqa: BLE001 - best effort
        pass
    return [], []


def samples_path(wd: WorkDir, source: int) -> Path:
    return wd.root / "scan" / f"{source:08x}.npz"


def _scan_mesh(rec: InputFile, cfg: CampusConfig, wd: WorkDir) -> list[str]:
    path = Path(rec.path)
    try:
        mesh = read_mesh(path, offset=cfg.inputs.mesh_offset, units_scale=cfg.inputs.units_scale)
    except InputError as e:
        rec.error = str(e)
        rec.lo, rec.hi = _salvage_mesh_bounds(path, cfg)
        return []
    if mesh.n_faces == 0:
        rec.error = str(InputError(path, "the mesh has no faces"))
        return []
    used = mesh.vertices[np.unique(mesh.faces)]
    rec.count = int(mesh.n_faces)
    rec.lo, rec.hi = used.min(axis=0).tolist(), used.max(axis=0).tolist()
    xyz, normals = surface_samples(mesh.vertices, mesh.faces, cfg.registration.target_spacing_m, seed=rec.source)
    out = samples_path(wd, rec.source)
    corner = np.asarray(rec.lo, np.float64)
    with atomic_path(out) as tmp, open(tmp, "wb") as f:  # float32 offsets from the file's corner: 0.1 mm in 2 km
        np.savez(f, corner=corner, xyz=(xyz - corner).astype(np.float32), normals=normals)
    return [str(out.relative_to(wd.root))]


def _scan_points(rec: InputFile, cfg: CampusConfig) -> None:
    path = Path(rec.path)
    try:
        info = read_header(path)
        s = cfg.inputs.units_scale
        rec.count = int(info.point_count)
        rec.lo, rec.hi = (info.bounds[0] * s).tolist(), (info.bounds[1] * s).tolist()
        rec.crs = info.crs
        if rec.count == 0:
            rec.error = str(InputError(path, "the point cloud holds no points"))
    except InputError as e:
        rec.error = str(e)
        rec.lo, rec.hi = _salvage_cloud_bounds(path, cfg)


def run_scan_file(path: str, kind: str, source: int, cfg: CampusConfig, wd: WorkDir) -> dict:
    """Scan one input file (skipped while its content is unchanged). Returns the unit summary with the
    file's :class:`InputFile` record as JSON under ``"record"``."""
    try:
        fp = fingerprint(path)
    except OSError as e:
        rec = InputFile(source, path, kind, "", error=str(InputError(path, f"cannot read ({e.strerror})")))
        return {"unit": f"{source:08x}", "status": "done", "record": rec.to_json(), "skipped": False}

    def work() -> Done:
        rec = InputFile(source, str(path), kind, fp)
        outputs = _scan_mesh(rec, cfg, wd) if kind == "mesh" else _scan_points(rec, cfg) or []
        if rec.error:
            log.info("input problem: %s", rec.error)  # reported once, in the run summary
        return Done(outputs=outputs, summary={"record": rec.to_json()})

    params = cfg.stage_params("scan") | {"kind": kind, "path": str(path)}
    return run_unit(wd, "scan", f"{source:08x}", fp, params, work)


def campus_frame(records: list[InputFile], cfg: CampusConfig) -> CampusFrame:
    """Frame of the campus from the scanned records: checks CRS, overlap and the float32 reach."""
    check_crs_is_projected(cfg.inputs.crs)
    crs = resolve_crs(cfg.inputs.crs, [r for r in records if r.kind == "points"])
    check_crs_is_projected(crs)
    check_overlap(records)
    return CampusFrame(origin=choose_origin(records, cfg.inputs.origin), crs=crs)
