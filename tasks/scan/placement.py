"""Where a mesh file lies: its offset to world metres, its CRS, and whether its seams weld across files.

An ordinary mesh file takes ``inputs.mesh_offset`` (and ``inputs.crs``). A file of a ContextCapture
production (:mod:`storage.formats.production`) takes the production's ``metadata.xml``: SRSOrigin is the offset
and SRS the CRS, and its tile seams are welded (:func:`tasks.ingest.kernels.vertex_ids`). The config
and the metadata must agree:

- ``inputs.mesh_offset`` left at its default (0, 0, 0): SRSOrigin is used.
- ``inputs.mesh_offset`` set and equal to SRSOrigin (within 1 mm): fine. Set and different: an error
  naming ``metadata.xml`` (a production says where it lies; a second, different answer is a mistake
  whichever is right, and guessing would move the model silently).
- ``inputs.crs`` set and different from the SRS: an error naming ``metadata.xml``.
- A production without ``metadata.xml`` (tiles in ``Tile_*`` folders) cannot be georeferenced: an error
  naming the folder, unless ``inputs.mesh_offset`` is set, which is then used for its tiles (one warning).
- A 3D Tiles tileset (``tileset.json``) is read in ECEF (:mod:`storage.formats.tiles3d`) and placed into
  ``inputs.crs`` (which it then needs), heights made orthometric with ``export.geoid_grid``'s geoid where
  the CRS's vertical datum needs one PROJ lacks (the inverse of the export); ``inputs.mesh_offset`` must stay 0.
- A production in a local ``ENU:<lat>,<lon>`` frame is placed into ``inputs.crs`` (which it then needs):
  SRSOrigin is the offset in the ENU frame, and :func:`place_mesh` moves the vertices to the CRS
  (:func:`storage.formats.srs.enu_to_crs`, exact to PROJ's precision; no flat-earth approximation).

Reads only ``metadata.xml`` files (a few hundred bytes each), never a mesh.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.production import Production
from storage.inputs.productions import production_of, production_root
from tasks.config import CampusConfig

log = logging.getLogger("ms3d.scan")

OFFSET_TOLERANCE_M = 1e-3


@dataclass(frozen=True)
class MeshPlacement:
    """offset: world metres added to the file's coordinates after ``inputs.units_scale``
    (:func:`storage.formats.meshes.read_mesh`); crs: from the production's metadata
    (None for an ordinary file); seam_key: the production key whose seams weld (None: an ordinary
    file); metadata: path of the ``metadata.xml`` used ("" when none); enu: (lat, lon) of the tangent
    point of a production in a local ENU frame (its offset is then in that frame, and :func:`place_mesh`
    moves the vertices into ``crs``), None otherwise."""

    offset: tuple[float, float, float]
    crs: str | None = None
    seam_key: int | None = None
    metadata: str = ""
    enu: tuple[float, float] | None = None
    ecef: bool = False
    geoid: str | None = None

    def to_json(self) -> dict:
        out = {"offset": list(self.offset), "crs": self.crs, "seam_key": self.seam_key, "metadata": self.metadata}
        if self.enu is not None:  # only then: placements of map-CRS productions keep their fingerprints
            out["enu"], out["geoid"] = list(self.enu), self.geoid
        if self.ecef:
            out["ecef"], out["geoid"] = True, self.geoid
        return out


def place_mesh(mesh, placement: MeshPlacement, path: str | Path = ""):
    """The mesh (``storage.formats.MeshData``, read with ``placement.offset``) in the campus CRS: unchanged
    for a map-CRS placement; its vertices moved from the ENU frame into ``placement.crs`` otherwise.
    Raises InputError naming ``path`` when PROJ cannot place it."""
    if placement.enu is None and not placement.ecef:
        return mesh
    from storage.formats.srs import enu_to_crs
    from storage.formats.tiles3d import ecef_to_crs

    try:
        if placement.ecef:
            mesh.vertices = ecef_to_crs(mesh.vertices, placement.crs, placement.geoid)
        else:
            mesh.vertices = enu_to_crs(mesh.vertices, *placement.enu, placement.crs, placement.geoid)
    except ValueError as e:
        raise InputError(path or placement.metadata, str(e)) from None
    return mesh


def _offset_configured(cfg: CampusConfig) -> bool:
    return any(float(v) != 0.0 for v in cfg.inputs.mesh_offset)


def placement_of(prod: Production | None, cfg: CampusConfig) -> MeshPlacement:
    """The placement of a file of production ``prod`` (None: an ordinary file) under ``cfg`` (module
    doc). Raises InputError when the config and the metadata disagree or the metadata is missing."""
    configured = tuple(float(v) for v in cfg.inputs.mesh_offset)
    if prod is None:
        return MeshPlacement(configured)  # type: ignore[arg-type]
    meta = prod.metadata
    if meta is None:
        if not _offset_configured(cfg):
            raise InputError(prod.root, "a ContextCapture production without metadata.xml: its tiles cannot be "
                                        "georeferenced; add the production's metadata.xml or set inputs.mesh_offset")
        return MeshPlacement(configured, None, prod.key, "")  # type: ignore[arg-type]
    if _offset_configured(cfg) and np.abs(np.subtract(configured, meta.origin)).max() > OFFSET_TOLERANCE_M:
        raise InputError(meta.path, f"SRSOrigin {list(meta.origin)} disagrees with inputs.mesh_offset "
                                    f"{list(configured)}: remove inputs.mesh_offset (the production's metadata "
                                    "places it) or fix the metadata")
    if meta.enu is not None:
        if not cfg.inputs.crs:
            raise InputError(meta.path, f"the production is in a local frame ({meta.srs}): set inputs.crs to the "
                                        "campus's projected CRS to place it there")
        return MeshPlacement(meta.origin, cfg.inputs.crs.strip().upper(), prod.key, meta.path, meta.enu,
                             geoid=cfg.export.geoid_grid)
    if cfg.inputs.crs and cfg.inputs.crs.strip().upper() != meta.srs:
        raise InputError(meta.path, f"SRS {meta.srs} disagrees with the configured inputs.crs {cfg.inputs.crs}: "
                                    "reproject the production or fix inputs.crs")
    return MeshPlacement(meta.origin, meta.srs, prod.key, meta.path)


def tileset_placement(path: str | Path, cfg: CampusConfig) -> MeshPlacement:
    """The placement of a 3D Tiles tileset (module doc). InputError naming it without ``inputs.crs`` or with
    an ``inputs.mesh_offset``."""
    if not cfg.inputs.crs:
        raise InputError(path, "a 3D Tiles tileset is in ECEF: set inputs.crs to the campus's projected CRS to "
                               "place it there")
    if _offset_configured(cfg):
        raise InputError(path, "a 3D Tiles tileset places itself (ECEF): remove inputs.mesh_offset")
    return MeshPlacement((0.0, 0.0, 0.0), cfg.inputs.crs.strip().upper(), None, "", None, True,
                         cfg.export.geoid_grid)


def mesh_placement(path: str | Path, cfg: CampusConfig) -> MeshPlacement:
    """The placement of one mesh file (module doc); reads its production's ``metadata.xml`` if any."""
    from storage.formats.tiles3d import is_tileset

    if is_tileset(path):
        return tileset_placement(path, cfg)
    return placement_of(production_of(path), cfg)


def check_productions(meshes: list[str] | tuple[str, ...], cfg: CampusConfig) -> list[Production]:
    """Check every production among the mesh files before anything is read: one InputError for bad or
    disagreeing metadata or a production without metadata (module doc); one warning line per production
    read without metadata on ``inputs.mesh_offset``. Returns the productions, by root."""
    roots: dict[str, Production] = {}
    for p in meshes:
        root = production_root(p)
        if root is not None and str(root) not in roots:
            prod = roots[str(root)] = production_of(p)
            placement_of(prod, cfg)
            if prod.metadata is None:
                log.warning("%s: a production without metadata.xml, placed by inputs.mesh_offset %s",
                            prod.root, list(cfg.inputs.mesh_offset))
    return sorted(roots.values(), key=lambda r: r.root)
