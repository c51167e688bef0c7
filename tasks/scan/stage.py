"""Scan the inputs once per content: bounds, counts, CRS, errors, and the mesh surface samples that
registration aligns to (the campus frame is then chosen from the records: :mod:`tasks.scan.frame`).

One scan unit per input file, keyed by the file's stable source id and skipped while its content
fingerprint is unchanged, so a nightly run over a thousand unchanged ContextCapture tiles reads none
of them. A mesh is read once here: its world bounds and face count go to the record, and area-weighted
samples of its surface (``registration.target_spacing_m``) go to ``scan/{source}.npz``, so registration
never re-reads a mesh and its target density does not depend on the tessellation (a coarse LoD2-like
model of a few hundred triangles is sampled as densely as a 10 cm MVS mesh).

A file that cannot be read is still scanned: its record carries the error and, when the file says
where it lies (a LAS header, the finite vertices of a broken mesh), its bounds, so that exactly the
tiles it covers are blocked (:mod:`tasks.scan.salvage`). A file whose bounds are unknown blocks no tile
and makes the campus incomplete.

A tile of a ContextCapture production is placed by its ``metadata.xml`` (:mod:`tasks.scan.placement`):
its record's CRS is the production's SRS, and its fingerprint covers the metadata too, so an edited
SRSOrigin re-scans and re-ingests every tile of the production.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from storage.contracts.surface_samples import samples_path, write_surface_samples
from storage.errors import InputError
from storage.formats.meshes import read_mesh
from storage.formats.points import read_header
from storage.inputs.identity import InputFile, fingerprint
from storage.inputs.remote import local_input
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.scan.placement import MeshPlacement, mesh_placement, place_mesh
from tasks.scan.salvage import salvage_cloud_bounds, salvage_mesh_bounds
from tasks.units import Done, run_unit

log = logging.getLogger("ms3d.scan")

MAX_SAMPLES_PER_FILE = 20_000_000  # registration crops and caps the samples near the MLS anyway


def surface_samples(vertices: np.ndarray, faces: np.ndarray, spacing_m: float, seed: int = 0):
    """Area-weighted samples of a triangle surface with their face normals
    (:func:`tasks.register.mesh_registration_target`). vertices: (n, 3) float64 metres; faces: (m, 3)
    int. Returns xyz (k, 3) float64 and normals (k, 3) float32."""
    from tasks.register import mesh_registration_target

    xyz, nrm = mesh_registration_target(vertices, faces, spacing_m, MAX_SAMPLES_PER_FILE, seed)
    return xyz, nrm.astype(np.float32)


def _scan_mesh(rec: InputFile, cfg: CampusConfig, wd: WorkDir, placement: MeshPlacement) -> list[str]:
    path = Path(local_input(rec.path, siblings=True))  # an input by URL is read from a staged copy
    rec.crs = placement.crs
    try:
        mesh = place_mesh(read_mesh(path, offset=placement.offset, units_scale=cfg.inputs.units_scale), placement, path)
    except InputError as e:
        rec.error = str(e)
        rec.lo, rec.hi = salvage_mesh_bounds(path, cfg, placement.offset)
        return []
    if mesh.n_faces == 0:
        rec.error = str(InputError(path, "the mesh has no faces"))
        return []
    used = mesh.vertices[np.unique(mesh.faces)]
    rec.count = int(mesh.n_faces)
    rec.warnings = list(mesh.warnings)
    rec.lo, rec.hi = used.min(axis=0).tolist(), used.max(axis=0).tolist()
    # one seed for every file: samples hashed from the faces' geometry alone, whatever the file's name or URL
    xyz, normals = surface_samples(mesh.vertices, mesh.faces, cfg.registration.target_spacing_m,
                                   seed=int(cfg.registration.seed))
    out = samples_path(wd, rec.source)
    write_surface_samples(out, xyz, normals, np.asarray(rec.lo, np.float64))
    return [str(out.relative_to(wd.root))]


def _scan_points(rec: InputFile, cfg: CampusConfig) -> None:
    path = Path(local_input(rec.path))
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
        rec.lo, rec.hi = salvage_cloud_bounds(path, cfg)


def run_scan_file(path: str, kind: str, source: int, cfg: CampusConfig, wd: WorkDir) -> dict:
    """Scan one input file (skipped while its content is unchanged). Returns the unit summary with the
    file's :class:`InputFile` record as JSON under ``"record"``."""
    placement = None
    try:
        fp = fingerprint(path)
        if kind == "mesh":
            placement = mesh_placement(path, cfg)
            if placement.metadata:
                fp = combine_fingerprints([fp, fingerprint(placement.metadata)])
    except (OSError, InputError) as e:
        err = e if isinstance(e, InputError) else InputError(path, f"cannot read ({e.strerror})")
        rec = InputFile(source, path, kind, "", error=str(err))
        return {"unit": f"{source:08x}", "status": "done", "record": rec.to_json(), "skipped": False}

    def work() -> Done:
        rec = InputFile(source, str(path), kind, fp)
        outputs = _scan_mesh(rec, cfg, wd, placement) if kind == "mesh" else _scan_points(rec, cfg) or []
        if rec.error:
            log.info("input problem: %s", rec.error)  # reported once, in the run summary
        return Done(outputs=outputs, summary={"record": rec.to_json()})

    params = cfg.stage_params("scan") | {"kind": kind, "path": str(path)}
    if placement is not None:
        params["placement"] = placement.to_json()
    return run_unit(wd, "scan", f"{source:08x}", fp, params, work)
