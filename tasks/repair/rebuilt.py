"""Edits of a region's rebuilt mesh (:class:`tasks.repair.mesh.RebuiltMesh`): faces dropped, free-surface
pieces added. Frames and units: campus-local metres."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from storage.vertex_ids import local_ids
from tasks.repair.mesh import RebuiltMesh, border_edges
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


def drop_unsupported(mesh: RebuiltMesh, replaced: np.ndarray, data, mls: np.ndarray, mls_n: np.ndarray, mc,
                     tree: cKDTree | None, cluster_m: float) -> tuple[RebuiltMesh, np.ndarray, dict]:
    """``mesh`` without the faces that rest on neither the MLS (p, 3) / normals (p, 3) nor the input zone
    surface of ``data`` (a RegionInput; :func:`tasks.repair.support.unsupported_faces` at
    ``mc.drop_unsupported_m``, reach ``mc.drop_unsupported_reach_m``), but for the weld: a face with two
    vertices on the retained border stays. The zone faces the remaining rebuild does not cover, and that no
    unexplained scan point (gap ``mc.keep_agreeing_m``, clusters within ``cluster_m``) contradicts, are no
    longer replaced (:mod:`tasks.repair.restore`, depth ``mc.restore_dropped_m``, 0: none; which faces are
    candidates: ``mc.restore_scope``).
    replaced: (mz,) bool over the zone faces. Returns (the mesh, replaced, counts)."""
    from tasks.repair.agree import unexplained_points
    from tasks.repair.restore import attached, restorable_faces

    border_ids = data.vertex_id[border_edges(data.zone_faces, data.context_faces, len(data.xyz)).ravel()]
    off = unsupported_faces(mesh.xyz, mesh.faces, mls, mls_n, data.xyz, data.zone_faces,
                            offset_m=mc.drop_unsupported_m, reach_m=mc.drop_unsupported_reach_m, tree=tree)
    off &= np.isin(mesh.vertex_id[mesh.faces], border_ids).sum(axis=1) < 2
    kept = without_faces(mesh, off)
    counts = {"unsupported_faces_dropped": int(off.sum()), "input_faces_restored": 0}
    scope_all = mc.restore_scope in ("uncovered", "any")
    if (off.any() or scope_all) and mc.restore_dropped_m > 0:
        mz = len(data.zone_faces)
        contradicted = np.zeros(mz, bool)
        if mc.restore_scope != "any":
            bad, fid = unexplained_points(mls, data.xyz, np.concatenate([data.zone_faces, data.context_faces]),
                                          gap_m=mc.keep_agreeing_m or mc.drop_unsupported_m, cluster_m=cluster_m,
                                          min_points=3)
            contradicted[fid[bad & (fid >= 0) & (fid < mz)]] = True
        back = restorable_faces(data.xyz, data.zone_faces, None if scope_all else (mesh.xyz, mesh.faces[off]),
                                (kept.xyz, kept.faces), contradicted, depth_m=mc.restore_dropped_m) & replaced
        if scope_all:  # only what continues the retained input: not an island inside the rebuild
            back = attached(data.zone_faces, data.context_faces, back, len(data.xyz))
        replaced = replaced & ~back
        counts["input_faces_restored"] = int(back.sum())
    return kept, replaced, counts


__all__ = ["drop_unsupported", "with_free", "without_faces"]
