"""Bounds of input files that failed to read, so that exactly the tiles they cover are blocked: the
finite vertices of a broken mesh, the header of a LAS/LAZ file whose points are unreadable. Best effort:
unknown bounds come back empty (the file then blocks no tile and the campus is incomplete).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.formats.las import las_header_bounds
from storage.formats.meshes import raw_vertices
from tasks.config import CampusConfig


def salvage_mesh_bounds(path: Path, cfg: CampusConfig, offset=None) -> tuple[list, list]:
    """Bounds of the finite vertices of a mesh that failed validation (to know which tiles it hits).
    offset: the file's (3,) world offset (:mod:`tasks.scan.placement`), default ``inputs.mesh_offset``."""
    try:
        v = raw_vertices(path)
        offset = cfg.inputs.mesh_offset if offset is None else offset
        v = v[np.isfinite(v).all(axis=1)] * cfg.inputs.units_scale + np.asarray(offset, np.float64)
        if len(v):
            return v.min(axis=0).tolist(), v.max(axis=0).tolist()
    except Exception:  # noqa: BLE001 - best effort; unknown bounds block no tile
        pass
    return [], []


def salvage_cloud_bounds(path: Path, cfg: CampusConfig) -> tuple[list, list]:
    """The header bounds of a LAS/LAZ file whose points are unreadable (to know which tiles it hits)."""
    try:
        lo, hi = las_header_bounds(path)
        if np.isfinite(lo).all() and np.isfinite(hi).all() and (hi >= lo).all() and (hi > lo).any():
            return (lo * cfg.inputs.units_scale).tolist(), (hi * cfg.inputs.units_scale).tolist()
    except Exception:  # noqa: BLE001 - best effort
        pass
    return [], []
