"""One region's geometric repair on arrays: fuse (§5.1) -> chart -> triangulate -> stitch (§5.2).

:func:`repair_region_geometry` takes a :class:`RegionInput` (what the stage read from the patch
stores) and returns a :class:`RegionGeometry`: the rebuilt mesh welded to the retained border, which
zone faces it replaces, the defect evidence and the figures of every step. No I/O here.

Frames and units: campus-local metres (float64 inside).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from storage.vertex_ids import local_ids
from tasks.geometry.triangles import face_areas, vertex_normals
from tasks.repair.agree import agreeing_faces
from tasks.repair.chart import zone_charts
from tasks.repair.coarsen import coarsen_flat, thin_with_detail
from tasks.repair.defect_types import DefectEvidence, classify_evidence, repair_plan
from tasks.repair.fill import SOURCE_FILL, unseen_samples
from tasks.repair.free import behind_surface, far_points, free_surface
from tasks.repair.fuse import (
    FusionParams,
    coverage_offsets,
    graph_cut_fuse,
    orient_like,
    pca_normals,
    thin_points,
)
from tasks.repair.keep import (
    covered_along_normal,
    expand_replaced,
    keep_faces,
    on_retained,
    overhead_faces,
    tidy_keep,
    top_faces,
    unseen_faces,
)
from tasks.repair.mesh import (
    RebuiltMesh,
    border_edges,
    border_gap,
    empty_mesh,
    poisson_depth_for,
    poisson_surface,
    rebuild_charts,
)
from tasks.repair.rebuilt import drop_unsupported, with_free
from tasks.repair.support import unsupported_share


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


def _thinned_mls(data: RegionInput, fc, zone_v: np.ndarray, vn: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, cKDTree | None]:
    """The region's MLS points without the dropped classes, thinned to ``fc.mls_spacing_m`` and to
    ``fc.detail_spacing_m`` where their surface is not flat (:func:`tasks.repair.coarsen.thin_with_detail`;
    neither when ``fc.thin`` is off), and the context points to ``fc.mls_spacing_m``; PCA normals oriented
    like the mesh. Returns (mls (p, 3), mls normals (p, 3), mls + context points (p + q, 3), their normals
    (p + q, 3), float64; the k-d tree of mls + context, None when empty: every later query of them shares it)."""
    keep = ~np.isin(data.mls_class, np.asarray(fc.drop_classes, np.uint8))
    mls, ctx = data.mls_xyz[keep], data.ctx_xyz if len(data.ctx_xyz) else np.zeros((0, 3))
    if fc.thin:
        mls = mls[thin_with_detail(mls, fc.mls_spacing_m, fc.detail_spacing_m, fc.detail_radius_m,
                                   fc.detail_tolerance_m)]
        ctx = ctx[thin_points(ctx, fc.mls_spacing_m)]
    both = np.concatenate([mls, ctx])
    tree = cKDTree(both) if len(both) else None
    if len(both) >= 3:
        nrm, _ = pca_normals(both, fc.normal_k, tree)
        nrm = orient_like(nrm, both, data.xyz[zone_v] if len(zone_v) else data.xyz, vn[zone_v] if len(zone_v) else vn)
    else:
        nrm = np.zeros((len(both), 3))
    return mls, nrm[: len(mls)], both, nrm, tree


def _hole_area_m2(data: RegionInput, zone_v: np.ndarray, mls: np.ndarray, mls_n: np.ndarray, spacing_m: float) -> float:
    """Area of MLS surface with no mesh near it, nor straight in front of or behind it (m², one
    ``spacing_m`` square per ``spacing_m`` voxel holding such a point, whatever the points' density)."""
    if not (len(mls) and len(zone_v)):
        return 0.0
    dmesh, j = cKDTree(data.xyz[zone_v]).query(mls)
    delta = data.xyz[zone_v][j] - mls
    lateral = np.linalg.norm(delta - np.einsum("ij,ij->i", delta, mls_n)[:, None] * mls_n, axis=1)
    hole = mls[(dmesh > 0.2) & (lateral > 0.2)]
    return float(len(thin_points(hole, spacing_m))) * spacing_m**2


def _conflicts(data: RegionInput, zone_v: np.ndarray, vn: np.ndarray, mls: np.ndarray, mls_n: np.ndarray, tc,
               params: FusionParams, stats: dict, mls_tree: cKDTree) -> np.ndarray | None:
    """(v,) bool zone vertices the MLS contradicts (a dissimilar MLS point within ``tc.conflict_radius_m``,
    or, with ``tc.front_m``, the vertex lies more than that in front of the MLS surface); None when the
    typed repair does not look for conflicts. Adds the counts to ``stats``."""
    if not (tc.enabled and tc.conflict_radius_m > 0 and len(mls)):
        return None
    from tasks.repair.fuse import best_similarity

    near = in_view(data.xyz[zone_v], vn[zone_v], mls, radius_m=tc.conflict_radius_m, cone_deg=tc.conflict_cone_deg,
                   pts_n=mls_n, min_cos=tc.conflict_min_cos, tree=mls_tree)
    sim = best_similarity(data.xyz[zone_v], vn[zone_v], mls, mls_n, mls_tree, params)
    conflict = near & (sim < params.similarity_threshold)
    stats["conflict"] = int(conflict.sum())
    if tc.front_m > 0:
        far = ~np.isfinite(mls_tree.query(data.xyz[zone_v], distance_upper_bound=tc.conflict_radius_m)[0])
        d2, j2 = mls_tree.query(data.xyz[zone_v][far], distance_upper_bound=tc.front_reach_m)
        ok = np.isfinite(d2)
        jj = np.where(ok, j2, 0)
        off = np.einsum("ij,ij->i", data.xyz[zone_v][far] - mls[jj], mls_n[jj])
        front = np.zeros(len(zone_v), bool)
        front[np.flatnonzero(far)[ok & (off > tc.front_m)]] = True
        conflict |= front
        stats["in_front"] = int(front.sum())
    return conflict


def in_view(xyz: np.ndarray, normals: np.ndarray, pts: np.ndarray, *, radius_m: float, cone_deg: float,
            k: int = 16, pts_n: np.ndarray | None = None, min_cos: float = 0.0, tree: cKDTree | None = None
            ) -> np.ndarray:
    """(v,) bool: vertices (v, 3) with one of their ``k`` nearest points (p, 3) within ``radius_m`` inside
    the double cone of half-angle ``cone_deg`` around the vertex normal (v, 3): in front of or behind the
    vertex, where the scan says something about it. A scanned wall top beside an unseen roof edge is not
    (it lies off to the side); ``cone_deg`` >= 90 accepts any point within the radius. Only the nearest
    ``k`` are asked, by design: when the scanned surface nearest to a vertex lies off to its side, the
    vertex is beyond the scan's edge, and a point farther down the wall that happens to fall in the cone
    says nothing of it (measured with k = 16 on the tiny campus: docs/repair.md). With ``pts_n`` (p, 3),
    the point must also face like the vertex (|cos| >= ``min_cos``): a parallel surface displaced, not a
    wall meeting the roof at its edge. tree: the k-d tree of ``pts`` when the caller has it."""
    if not (len(xyz) and len(pts)):
        return np.zeros(len(xyz), bool)
    d, j = (tree if tree is not None else cKDTree(pts)).query(xyz, k=min(k, len(pts)), distance_upper_bound=radius_m)
    d, j = d.reshape(len(xyz), -1), j.reshape(len(xyz), -1)
    ok = np.isfinite(d)
    if cone_deg >= 90:
        return ok.any(axis=1)
    delta = pts[np.where(ok, j, 0)] - xyz[:, None, :]
    axial = np.abs(np.einsum("vkd,vd->vk", delta, normals))
    lateral = np.sqrt(np.maximum(np.einsum("vkd,vkd->vk", delta, delta) - axial**2, 0.0))
    hit = ok & (lateral <= axial * np.tan(np.radians(cone_deg)))
    if pts_n is not None and min_cos > 0:
        hit &= np.abs(np.einsum("vkd,vd->vk", pts_n[np.where(ok, j, 0)], normals)) >= min_cos
    return hit.any(axis=1)


def _mesh_points(fused_xyz: np.ndarray, fused_n: np.ndarray, fused_src: np.ndarray, fused_vertex: np.ndarray, fc, mc,
                 stats: dict) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points the charts are triangulated from: the fused points, or (``mesh.method`` poisson, at least
    10 points) the Poisson surface's vertices near them. Returns ((k, 3) xyz, (k, 3) unit normals, (k,) int8
    source, (k,) int64 original vertex index or -1)."""
    if mc.method != "poisson" or len(fused_xyz) < 10:
        return fused_xyz, fused_n, fused_src, fused_vertex
    ext = float(np.ptp(fused_xyz, axis=0).max())
    depth = poisson_depth_for(ext, fc.mls_spacing_m * 1.5, hi=mc.poisson_depth)
    pv, pn, _ = poisson_surface(fused_xyz, fused_n, depth, mc.poisson_trim_quantile)
    near = cKDTree(fused_xyz).query(pv, distance_upper_bound=3 * fc.mls_spacing_m)[0] < np.inf
    stats["poisson"] = {"depth": depth, "vertices": len(pv), "kept": int(near.sum())}
    return pv[near], pn[near], np.full(int(near.sum()), 2, np.int8), np.full(int(near.sum()), -1)


def _coarsened(pts: np.ndarray, src: np.ndarray, mc, stats: dict) -> np.ndarray:
    """(k,) bool: the triangulation's points to keep, with the MLS points (source 1) of flat stretches thinned
    to ``mc.flat_spacing_m`` (:mod:`tasks.repair.coarsen`); mesh vertices and Poisson points stay."""
    keep = np.ones(len(pts), bool)
    mls = np.flatnonzero(src == 1)
    if mc.flat_spacing_m <= 0 or len(mls) < 6:
        return keep
    drop = np.ones(len(mls), bool)
    drop[coarsen_flat(pts[mls], mc.flat_spacing_m, mc.flat_tolerance_m)] = False
    stats["flat_dropped"] = int(drop.sum())
    keep[mls[drop]] = False
    return keep


def _free_part(data: RegionInput, mls: np.ndarray, mc, fc, stats: dict) -> tuple[np.ndarray, np.ndarray]:
    """The free surface (:mod:`tasks.repair.free`) of the region's MLS points that no chart takes (farther
    than ``mc.max_map_distance_m`` from the zone's faces), no retained face explains (farther than
    ``mc.free_off_surface_m`` from the context faces) and that lie behind the surface (inside the solid):
    ((v, 3), (f, 3)); empty when ``mc.free_surface`` is off."""
    if not mc.free_surface or not len(mls):
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    far = far_points(mls, data.xyz, data.zone_faces, mc.max_map_distance_m)
    far[far] = far_points(mls[far], data.xyz, data.context_faces, mc.free_off_surface_m)
    faces = np.concatenate([data.zone_faces, data.context_faces])
    far[far] = behind_surface(mls[far], data.xyz, faces, mc.free_off_surface_m)
    v, f, st = free_surface(mls[far], min_points=mc.free_min_points, normal_k=fc.normal_k)
    stats["free"] = st
    return v, f


def _finish_stats(stats: dict, data: RegionInput, mesh: RebuiltMesh, replaced: np.ndarray, zone_area: float) -> None:
    """Add the border gap between the rebuilt charts and what stays (context faces and non-disc zone
    pieces left in place) and the rebuilt figures to ``stats``."""
    bord_used = border_edges(data.zone_faces[replaced], data.context_faces, len(data.xyz))
    stats["border"] = border_gap(data.xyz[bord_used], data.vertex_id[bord_used], mesh)
    stats["rebuilt_faces"] = mesh.n_faces
    stats["rebuilt_area_m2"] = float(face_areas(mesh.xyz, mesh.faces, np.float64).sum()) if mesh.n_faces else 0.0
    stats["zone_area_m2"] = zone_area
    stats["mesh"] = mesh.stats


def repair_region_geometry(data: RegionInput, cfg) -> RegionGeometry:
    """Fuse, classify the defect, triangulate and stitch one region. cfg: ``RepairConfig``.

    Zone faces the MLS did not see (``mesh.keep_unseen_m``, :mod:`tasks.repair.keep`) and those it agrees
    with (``mesh.keep_agreeing_m``, :mod:`tasks.repair.agree`) join the retained mesh first; the rest is
    rebuilt and stitched to them. ``replaced`` is over all zone faces."""
    t0 = time.perf_counter()
    fc, mc = cfg.fusion, cfg.mesh
    vn = vertex_normals(data.xyz, np.concatenate([data.zone_faces, data.context_faces]),
                        stored_normals=data.face_normals, order="corners")
    thinned = _thinned_mls(data, fc, np.unique(data.zone_faces), vn)
    keep = np.zeros(len(data.zone_faces), bool)
    if mc.keep_unseen_m > 0 and len(data.zone_faces):
        _, _, both, nrm, both_tree = thinned
        oh = overhead_faces(data.xyz, data.zone_faces, both, min_height_m=mc.overhead_min_height_m)
        top = oh & top_faces(data.xyz, data.zone_faces)
        oh_v, top_v = np.zeros(len(data.xyz), bool), np.zeros(len(data.xyz), bool)
        oh_v[data.zone_faces[oh].ravel()] = True
        top_v[data.zone_faces[top].ravel()] = True
        covered = covered_along_normal(data.xyz, vn, both, nrm, depth_m=fc.point_depth_m,
                                       lateral_m=1.5 * fc.mls_spacing_m, overhead=oh_v, top=top_v, tree=both_tree)
        keep = unseen_faces(data.xyz, data.zone_faces, both, covered, clear_m=mc.keep_unseen_m, step_m=mc.fill_step_m,
                            overhead=oh, mls_n=nrm, top=top, tree=both_tree)
        keep = tidy_keep(data.xyz, data.zone_faces, keep, oh, mc.keep_min_area_m2)
        if keep.all() and not (keep & oh).any():  # all unseen: the typed plan leaves it
            keep = np.zeros(len(keep), bool)
    n_unseen = int(keep.sum())
    agree_stats: dict = {}
    if mc.keep_agreeing_m > 0 and len(data.zone_faces) and len(thinned[2]):
        keep = keep | agreeing_faces(data.xyz, data.zone_faces, data.context_faces, thinned[2],
                                     gap_m=mc.keep_agreeing_m, band_m=mc.agree_band_m,
                                     cluster_m=3 * fc.mls_spacing_m, min_area_m2=mc.keep_min_area_m2,
                                     stats=agree_stats)
    prep = time.perf_counter() - t0
    geo = _repair(keep_faces(data, keep), cfg, vn, thinned)
    geo.stats["kept_unseen_faces"] = n_unseen
    if agree_stats:
        geo.stats["agreeing"] = agree_stats["agreeing"] | {"kept_faces": int(keep.sum()) - n_unseen}
    sec = geo.stats.setdefault("seconds", {})  # thinning, PCA normals and the unseen faces, before the steps
    geo.stats["seconds"] = {"prepare": prep, **sec, "total": prep + sec.get("total", 0.0)}
    if len(keep) and keep.all():  # nothing of the zone left to rebuild: the plan of an empty zone says nothing
        why = "unseen by the MLS (overhead or clear of its points)" if n_unseen == len(keep) else \
            "the scan agrees with it or does not see it"
        geo.stats["plan"] = f"{why}: the input mesh kept" \
            + (f", {geo.mesh.n_faces} free-surface faces added" if geo.mesh.n_faces else "")
    return replace(geo, replaced=expand_replaced(geo.replaced, keep)) if keep.any() else geo


def _repair(data: RegionInput, cfg, vn: np.ndarray, thinned: tuple) -> RegionGeometry:
    """:func:`repair_region_geometry` on the zone left to rebuild; vn: (n, 3) vertex normals; thinned: the
    region's thinned MLS points (:func:`_thinned_mls`)."""
    t0 = time.perf_counter()
    fc, mc, tc = cfg.fusion, cfg.mesh, cfg.typed
    params = FusionParams.from_config(fc)
    mz = len(data.zone_faces)
    zone_v = np.unique(data.zone_faces)
    locked = np.isin(zone_v, border_edges(data.zone_faces, data.context_faces, len(data.xyz)).ravel())
    mls, mls_n, both, nrm, tree = thinned
    stats: dict = {"mls_points": len(data.mls_xyz), "mls_thinned": len(mls)}
    if mc.retained_point_m > 0 and len(mls) and len(data.context_faces) and mz:
        off = on_retained(mls, data.xyz, data.zone_faces, data.context_faces, mc.retained_point_m)
        stats["on_retained"] = int(off.sum())  # the retained surface explains them: not rebuilt into a chart
        mls, mls_n = mls[~off], mls_n[~off]
    mls_tree = cKDTree(mls) if len(mls) else None  # the fused MLS points' tree: conflicts and the graph cut
    t1 = time.perf_counter()
    # evidence (typed repair) from the MLS surface over zone + context
    covered, offset = coverage_offsets(data.xyz[zone_v], both, nrm, tree, fc.point_depth_m, 1.5 * fc.mls_spacing_m)
    zone_area = float(face_areas(data.xyz, data.zone_faces, np.float64).sum())
    topo = zone_charts(data.xyz, data.zone_faces, data.context_faces, data.near_zone, mc.max_hole_loop_m)
    ev = classify_evidence(covered, offset, offset_m=tc.offset_m,
                           hole_area_m2=_hole_area_m2(data, zone_v, mls, mls_n, fc.mls_spacing_m),
                           open_loop_m=topo.hole_length_m, zone_area_m2=zone_area, min_coverage=tc.min_coverage)
    conflict = _conflicts(data, zone_v, vn, mls, mls_n, tc, params, stats, mls_tree)
    plan = repair_plan(ev, covered, offset, typed=tc.enabled, offset_m=tc.offset_m, conflict=conflict,
                       uncovered=tc.uncovered)
    free = _free_part(data, mls, mc, fc, stats)
    if plan.mesh_only:
        mls, mls_n, mls_tree = mls[:0], mls_n[:0], None
    stats |= {"plan": plan.reason, "charts": len(topo.charts), "non_disc_faces": len(topo.rejected)}
    t2 = time.perf_counter()
    if not plan.rebuild or not topo.charts:
        stats["seconds"] = {"total": time.perf_counter() - t0}
        mesh = with_free(empty_mesh(), *free)
        if mesh.n_faces:
            _finish_stats(stats, data, mesh, np.zeros(mz, bool), zone_area)
        return RegionGeometry(mesh, np.zeros(mz, bool), ev, np.zeros((0, 3)), np.zeros(0, np.int8), stats)
    fr = graph_cut_fuse(data.xyz[zone_v], vn[zone_v], mls, mls_n, params, forced=plan.forced & ~locked, locked=locked,
                        mls_tree=mls_tree)
    stats["fusion"] = {"vertices": len(zone_v), "replaced": int(fr.replaced.sum()),
                       "accepted": int(fr.accepted.sum()), "rejected": int((~fr.accepted).sum()),
                       "forced": int((plan.forced & ~locked).sum()), "energy": fr.energy}
    kept_v = zone_v[~fr.replaced & ~locked]
    acc, acc_n = mls[fr.accepted], mls_n[fr.accepted]
    fused_xyz = np.concatenate([data.xyz[kept_v], acc])
    fused_src = np.r_[np.zeros(len(kept_v), np.int8), np.ones(len(acc), np.int8)]
    t3 = time.perf_counter()
    pts, pn, src, pvert = _mesh_points(fused_xyz, np.concatenate([vn[kept_v], acc_n]), fused_src,
                                       np.r_[kept_v, np.full(len(acc), -1)], fc, mc, stats)
    k = _coarsened(pts, src, mc, stats)
    pts, pn, src, pvert = pts[k], pn[k], src[k], pvert[k]
    cleared = zone_v[fr.replaced & ~locked] if mc.fill_clears_replaced else zone_v[:0]
    fill = unseen_samples(data.xyz, data.zone_faces, fused_xyz, data.xyz[cleared],
                          step_m=mc.fill_step_m, reach_m=mc.max_map_distance_m)
    stats["filled"] = len(fill)
    pts, src = np.concatenate([pts, fill]), np.r_[src, np.full(len(fill), SOURCE_FILL, np.int8)]
    pvert, pn = np.r_[pvert, np.full(len(fill), -1)], np.concatenate([pn, np.zeros((len(fill), 3))])
    vxyz, vids = seam_positions(data, zone_v, fr.replaced, acc, acc_n, topo)
    stats["seam_vertices_moved"] = int((vids != data.vertex_id).sum())
    mesh = rebuild_charts(topo.charts, vids, pts, src, pvert, max_map_distance_m=mc.max_map_distance_m,
                          border_margin_m=0.5 * fc.mls_spacing_m, max_edge_m=mc.max_edge_m, vertex_xyz=vxyz,
                          pts_normal=pn, stand_off_m=mc.stand_off_m)
    replaced = np.ones(mz, bool)
    replaced[topo.rejected] = False
    stats["unsupported_share"] = unsupported_share(mesh.xyz, mesh.faces, both, nrm, data.xyz, data.zone_faces,
                                                   tree=tree)
    if stats["unsupported_share"] > mc.max_unsupported_share:  # invented geometry: the input mesh stays
        stats["plan"] = f"fallback: {stats['unsupported_share']:.0%} of the rebuilt surface unsupported"
        mesh, replaced = empty_mesh(), np.zeros(mz, bool)
    elif mc.drop_unsupported_m > 0 and mesh.n_faces:  # chords across a scan gap, a corner, a recess: left open
        mesh, replaced, dropped = drop_unsupported(mesh, replaced, data, both, nrm, mc, tree, 3 * fc.mls_spacing_m)
        stats |= dropped
    mesh = with_free(mesh, *free)
    t4 = time.perf_counter()
    _finish_stats(stats, data, mesh, replaced, zone_area)
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
        ids[m] = local_ids(m, "seam")
    return xyz, ids
