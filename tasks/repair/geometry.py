"""One region's geometric repair on arrays: fuse (§5.1) -> chart -> triangulate -> stitch (§5.2).

:func:`repair_region_geometry` takes a :class:`RegionInput` (what the stage read from the patch
stores) and returns a :class:`RegionGeometry`: the rebuilt mesh welded to the retained border, which
zone faces it replaces, the defect evidence and the figures of every step. No I/O here.

Frames and units: campus-local metres (float64 inside).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from tasks.repair.defect_types import DefectEvidence, classify_evidence, repair_plan
from tasks.repair.fuse import (
    FusionParams,
    coverage_offsets,
    graph_cut_fuse,
    orient_like,
    pca_normals,
    thin_points,
    vertex_normals,
)
from tasks.repair.mesh import (
    RebuiltMesh,
    border_edges,
    border_gap,
    empty_mesh,
    poisson_depth_for,
    poisson_surface,
    rebuild_charts,
    triangle_areas,
)
from tasks.repair.chart import zone_charts


@dataclass(frozen=True)
class RegionInput:
    """A region's data, read from the stores.

    xyz: (n, 3) float64 vertex table (zone + context), vertex_id: (n,) int64 their campus-unique ids;
    zone_faces: (mz, 3) int64 into xyz (the faces of the rebuilt patches); context_faces: (mc, 3)
    (the ring of retained faces around them); near_zone: (n,) bool vertices within a cell of the zone;
    mls_xyz: (p, 3) float64 MLS points of the rebuilt patches; mls_class: (p,) uint8 ASPRS class;
    ctx_xyz: (q, 3) MLS points of the context patches (normals, coverage); spacing of the grid not needed.
    """

    xyz: np.ndarray
    vertex_id: np.ndarray
    zone_faces: np.ndarray
    context_faces: np.ndarray
    near_zone: np.ndarray
    mls_xyz: np.ndarray
    mls_class: np.ndarray
    ctx_xyz: np.ndarray
    face_normals: np.ndarray | None = None  # (mz + mc, 3) stored normals of zone then context faces


@dataclass(frozen=True)
class RegionGeometry:
    """mesh: the rebuilt mesh (empty when the region is left to the mesh); replaced: (mz,) bool zone
    faces it replaces; evidence: the defect evidence; fused_xyz / fused_source: the fused point set
    (0 mesh vertex, 1 MLS); stats: figures of each step (counts, seconds, border gap)."""

    mesh: RebuiltMesh
    replaced: np.ndarray
    evidence: DefectEvidence
    fused_xyz: np.ndarray
    fused_source: np.ndarray
    stats: dict = field(default_factory=dict)


def repair_region_geometry(data: RegionInput, cfg) -> RegionGeometry:
    """Fuse, classify the defect, triangulate and stitch one region. cfg: ``RepairConfig``."""
    t0 = time.perf_counter()
    fc, mc, tc = cfg.fusion, cfg.mesh, cfg.typed
    params = FusionParams.from_config(fc)
    mz = len(data.zone_faces)
    stats: dict = {}
    allf = np.concatenate([data.zone_faces, data.context_faces])
    vn = vertex_normals(data.xyz, allf, data.face_normals)
    zone_v = np.unique(data.zone_faces)
    bord = border_edges(data.zone_faces, data.context_faces, len(data.xyz))
    locked = np.isin(zone_v, bord.ravel())
    # MLS: drop classes, thin, normals oriented like the mesh
    keep = ~np.isin(data.mls_class, np.asarray(fc.drop_classes, np.uint8))
    mls = data.mls_xyz[keep]
    mls = mls[thin_points(mls, fc.mls_spacing_m)]
    ctx = data.ctx_xyz[thin_points(data.ctx_xyz, fc.mls_spacing_m)] if len(data.ctx_xyz) else np.zeros((0, 3))
    both = np.concatenate([mls, ctx])
    if len(both) >= 3:
        nrm, _ = pca_normals(both, fc.normal_k)
        nrm = orient_like(nrm, both, data.xyz[zone_v] if len(zone_v) else data.xyz, vn[zone_v] if len(zone_v) else vn)
    else:
        nrm = np.zeros((len(both), 3))
    mls_n = nrm[: len(mls)]
    stats["mls_points"] = len(data.mls_xyz)
    stats["mls_thinned"] = len(mls)
    t1 = time.perf_counter()
    # evidence (typed repair) from the MLS surface over zone + context
    tree = cKDTree(both) if len(both) else None
    covered, offset = coverage_offsets(data.xyz[zone_v], both, nrm, tree, fc.point_depth_m, 1.5 * fc.mls_spacing_m)
    zone_area = float(triangle_areas(data.xyz, data.zone_faces).sum())
    if len(mls) and len(zone_v):  # MLS surface with no mesh near it, nor straight in front / behind it
        dmesh, j = cKDTree(data.xyz[zone_v]).query(mls)
        delta = data.xyz[zone_v][j] - mls
        lateral = np.linalg.norm(delta - np.einsum("ij,ij->i", delta, mls_n)[:, None] * mls_n, axis=1)
        hole_area = float(((dmesh > 0.2) & (lateral > 0.2)).sum()) * fc.mls_spacing_m**2
    else:
        hole_area = 0.0
    topo = zone_charts(data.xyz, data.zone_faces, data.context_faces, data.near_zone, mc.max_hole_loop_m)
    ev = classify_evidence(covered, offset, offset_m=tc.offset_m, hole_area_m2=hole_area,
                           open_loop_m=topo.hole_length_m, zone_area_m2=zone_area, min_coverage=tc.min_coverage)
    conflict = None
    if tc.enabled and tc.conflict_radius_m > 0 and len(mls):
        from tasks.repair.fuse import best_similarity

        dn = cKDTree(mls).query(data.xyz[zone_v], distance_upper_bound=tc.conflict_radius_m)[0]
        sim = best_similarity(data.xyz[zone_v], vn[zone_v], mls, mls_n, cKDTree(mls), params)
        conflict = np.isfinite(dn) & (sim < params.similarity_threshold)
        stats["conflict"] = int(conflict.sum())
        if tc.front_m > 0:
            far = ~np.isfinite(dn)
            d2, j2 = cKDTree(mls).query(data.xyz[zone_v][far], distance_upper_bound=tc.front_reach_m)
            ok = np.isfinite(d2)
            jj = np.where(ok, j2, 0)
            off = np.einsum("ij,ij->i", data.xyz[zone_v][far] - mls[jj], mls_n[jj])
            front = np.zeros(len(zone_v), bool)
            front[np.flatnonzero(far)[ok & (off > tc.front_m)]] = True
            conflict |= front
            stats["in_front"] = int(front.sum())
    plan = repair_plan(ev, covered, offset, typed=tc.enabled, offset_m=tc.offset_m, conflict=conflict,
                       uncovered=tc.uncovered)
    if plan.mesh_only:
        mls, mls_n = mls[:0], mls_n[:0]
    stats["plan"] = plan.reason
    stats["charts"] = len(topo.charts)
    stats["non_disc_faces"] = len(topo.rejected)
    t2 = time.perf_counter()
    if not plan.rebuild or not topo.charts:
        stats["seconds"] = {"total": time.perf_counter() - t0}
        return RegionGeometry(empty_mesh(), np.zeros(mz, bool), ev, np.zeros((0, 3)), np.zeros(0, np.int8), stats)
    fr = graph_cut_fuse(data.xyz[zone_v], vn[zone_v], mls, mls_n, params, forced=plan.forced & ~locked, locked=locked)
    stats["fusion"] = {"vertices": len(zone_v), "replaced": int(fr.replaced.sum()),
                       "accepted": int(fr.accepted.sum()), "rejected": int((~fr.accepted).sum()),
                       "forced": int((plan.forced & ~locked).sum()), "energy": fr.energy}
    kept_v = zone_v[~fr.replaced & ~locked]
    acc = mls[fr.accepted]
    acc_n = mls_n[fr.accepted]
    fused_xyz = np.concatenate([data.xyz[kept_v], acc])
    fused_src = np.r_[np.zeros(len(kept_v), np.int8), np.ones(len(acc), np.int8)]
    fused_vertex = np.r_[kept_v, np.full(len(acc), -1)]
    t3 = time.perf_counter()
    if mc.method == "poisson" and len(fused_xyz) >= 10:
        fused_n = np.concatenate([vn[kept_v], acc_n])
        ext = float(np.ptp(fused_xyz, axis=0).max())
        depth = poisson_depth_for(ext, fc.mls_spacing_m * 1.5, hi=mc.poisson_depth)
        pv, _, _ = poisson_surface(fused_xyz, fused_n, depth, mc.poisson_trim_quantile)
        near = cKDTree(fused_xyz).query(pv, distance_upper_bound=3 * fc.mls_spacing_m)[0] < np.inf
        pts, src, pvert = pv[near], np.full(int(near.sum()), 2, np.int8), np.full(int(near.sum()), -1)
        stats["poisson"] = {"depth": depth, "vertices": len(pv), "kept": int(near.sum())}
    else:
        pts, src, pvert = fused_xyz, fused_src, fused_vertex
    vxyz, vids = seam_positions(data, zone_v, fr.replaced, acc, acc_n, topo)
    stats["seam_vertices_moved"] = int((vids != data.vertex_id).sum())
    mesh = rebuild_charts(topo.charts, vids, pts, src, pvert, max_map_distance_m=mc.max_map_distance_m,
                          border_margin_m=0.5 * fc.mls_spacing_m, max_edge_m=mc.max_edge_m, vertex_xyz=vxyz)
    t4 = time.perf_counter()
    replaced = np.ones(mz, bool)
    replaced[topo.rejected] = False
    zone_used = data.zone_faces[replaced]
    bord_used = border_edges(zone_used, data.context_faces, len(data.xyz))
    gap = border_gap(data.xyz[bord_used], data.vertex_id[bord_used], mesh)
    # the border between rebuilt charts and non-disc zone pieces left in place
    stats["border"] = gap
    stats["rebuilt_faces"] = mesh.n_faces
    stats["rebuilt_area_m2"] = float(triangle_areas(mesh.xyz, mesh.faces).sum()) if mesh.n_faces else 0.0
    stats["zone_area_m2"] = zone_area
    stats["mesh"] = mesh.stats
    stats["seconds"] = {"normals": t1 - t0, "evidence": t2 - t1, "fusion": t3 - t2, "mesh": t4 - t3,
                        "total": time.perf_counter() - t0}
    return RegionGeometry(mesh, replaced, ev, fused_xyz, fused_src, stats)


def seam_positions(data: RegionInput, zone_v: np.ndarray, replaced: np.ndarray, acc: np.ndarray, acc_n: np.ndarray,
                   topo) -> tuple[np.ndarray, np.ndarray]:
    """Output positions and ids of the region's vertices: chart boundary vertices that are neither on the
    retained border nor on the mesh's own edge (seams cut to make a disc) and that the fusion replaced
    are projected onto the plane of the nearest accepted MLS point and get a new id (-(2**40) - index)."""
    from tasks.repair.chart import boundary_edges as open_edges

    xyz, ids = data.xyz.copy(), data.vertex_id.copy()
    if not len(acc) or not topo.charts:
        return xyz, ids
    on_loop = np.zeros(len(xyz), bool)
    for ch in topo.charts:
        v = ch.vertex[ch.loop]
        on_loop[v[v >= 0]] = True
    fixed = np.zeros(len(xyz), bool)
    fixed[border_edges(data.zone_faces, data.context_faces, len(xyz)).ravel()] = True
    fixed[open_edges(np.concatenate([data.zone_faces, data.context_faces]), len(xyz)).ravel()] = True
    rep = np.zeros(len(xyz), bool)
    rep[zone_v[replaced]] = True
    move = np.flatnonzero(on_loop & ~fixed & rep)
    if len(move):
        d, j = cKDTree(acc).query(xyz[move], distance_upper_bound=1.0)
        ok = np.isfinite(d)
        m, j = move[ok], j[ok]
        off = np.einsum("ij,ij->i", xyz[m] - acc[j], acc_n[j])
        xyz[m] -= off[:, None] * acc_n[j]
        ids[m] = -(1 << 40) - m
    return xyz, ids
