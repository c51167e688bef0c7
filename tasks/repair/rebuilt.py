"""Edits of a region's rebuilt mesh (:class:`tasks.repair.mesh.RebuiltMesh`): faces dropped, free-surface
pieces added. Frames and units: campus-local metres."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from storage.vertex_ids import local_ids
from tasks.repair.mesh import RebuiltMesh
from tasks.repair.support import unsupported_faces


def without_faces(mesh: RebuiltMesh, drop: np.ndarray) -> RebuiltMesh:
    """``mesh`` without the faces ``drop`` (m,) bool and the vertices no face uses any more."""
    if not drop.any():
        return mesh
    faces = mesh.faces[~drop]
    used = np.zeros(len(mesh.xyz), bool)
    used[faces.ravel()] = True
    new = np.cumsum(used) - 1
    return RebuiltMesh(mesh.xyz[used], mesh.vertex_id[used], new[faces], mesh.source[used], mesh.chart[~drop],
                       mesh.stats)


def with_free(mesh: RebuiltMesh, v: np.ndarray, f: np.ndarray) -> RebuiltMesh:
    """``mesh`` plus free-surface vertices (new, local ids; source 1: from MLS points) and faces (chart -1)."""
    if not len(f):
        return mesh
    n = len(mesh.xyz)
    return RebuiltMesh(np.concatenate([mesh.xyz, v]), np.r_[mesh.vertex_id, local_ids(np.arange(len(v)), "free")],
                       np.concatenate([mesh.faces, f + n]), np.r_[mesh.source, np.ones(len(v), np.int8)],
                       np.r_[mesh.chart, np.full(len(f), -1, np.int32)], mesh.stats)


def drop_unsupported(mesh: RebuiltMesh, mls: np.ndarray, mls_n: np.ndarray, zone_xyz: np.ndarray,
                     zone_faces: np.ndarray, border_ids: np.ndarray, mc, tree: cKDTree | None
                     ) -> tuple[RebuiltMesh, int]:
    """``mesh`` without the faces that rest on neither the MLS (p, 3) / normals (p, 3) nor the input zone
    surface (:func:`tasks.repair.support.unsupported_faces` at ``mc.drop_unsupported_m``, reach
    ``mc.drop_unsupported_reach_m``), but for the weld: a face with two vertices among ``border_ids`` (the
    retained border's vertex ids) stays. Returns (the mesh, faces dropped)."""
    off = unsupported_faces(mesh.xyz, mesh.faces, mls, mls_n, zone_xyz, zone_faces, offset_m=mc.drop_unsupported_m,
                            reach_m=mc.drop_unsupported_reach_m, tree=tree)
    off &= np.isin(mesh.vertex_id[mesh.faces], border_ids).sum(axis=1) < 2
    return without_faces(mesh, off), int(off.sum())


__all__ = ["drop_unsupported", "with_free", "without_faces"]
