"""Input faces put back under a dropped chord (tasks.repair.restore via tasks.repair.rebuilt.drop_unsupported):
the roof the scan never saw stays when the chord that replaced it goes; a face the scan contradicts does not
come back; with ``restore_dropped_m`` 0 the roof is lost as before. The default scope ("uncovered") also keeps
input the rebuild never reached, where it continues the retained input."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.config.repair import RepairConfig
from tasks.repair.mesh import RebuiltMesh
from tasks.repair.rebuilt import drop_unsupported
from tasks.repair.region_geometry import RegionInput

DROPPED = RepairConfig.model_validate({"mesh": {"restore_scope": "dropped"}}).mesh  # the chord rule alone


def _grid(x0, x1, nx, a0, a1, na, plane):
    """A regular triangulated rectangle: plane "wall" (x-z at y = 0) or "roof" (x-y at z = 3)."""
    xs, as_ = np.linspace(x0, x1, nx + 1), np.linspace(a0, a1, na + 1)
    v = np.array([[x, 0.0, a] if plane == "wall" else [x, a, 3.0] for x in xs for a in as_])
    idx = lambda i, j: i * (na + 1) + j
    f = [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)] for i in range(nx) for j in range(na)]
    f += [[idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)] for i in range(nx) for j in range(na)]
    return v, np.array(f, np.int64)


def _case():
    """A wall (y = 0, z 0-3) whose lower part was sunk 20 cm into the building (an offset: the scan shows the
    true wall), and a roof strip (z = 3, y 0-1) the street scanner never saw; the rebuild made a good wall
    and one chord from the wall's top to the roof's back edge, 0.4-0.7 m off both."""
    wv, wf = _grid(0, 4, 8, 0, 3, 6, "wall")
    wv[wv[:, 2] < 1.4, 1] += 0.2  # the offset part of the input
    rv, rf = _grid(0, 4, 8, 0, 1, 2, "roof")
    xyz = np.concatenate([wv, rv])
    zone = np.concatenate([wf, rf + len(wv)])
    rng = np.random.default_rng(5)
    pts = np.c_[rng.uniform(0, 4, 20000), rng.normal(0, 0.005, 20000), rng.uniform(0.05, 2.95, 20000)]
    nrm = np.tile([0.0, -1.0, 0.0], (len(pts), 1))
    data = RegionInput(xyz=xyz, vertex_id=np.arange(len(xyz)), zone_faces=zone,
                       context_faces=np.zeros((0, 3), np.int64), near_zone=np.ones(len(xyz), bool), mls_xyz=pts,
                       mls_class=np.zeros(len(pts), np.uint8), ctx_xyz=np.zeros((0, 3)))
    good = np.array([[0, 0, 0], [4, 0, 0], [4, 0, 3], [0, 0, 3]], float)  # the rebuilt wall, on the scan
    chord = np.array([[0, 0, 3], [4, 0, 3], [4, 1, 3.6], [0, 1, 3.6]], float)  # up and over the roof
    mx = np.concatenate([good, chord])
    mf = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]], np.int64)
    mesh = RebuiltMesh(mx, -1 - np.arange(len(mx)), mf, np.ones(len(mx), np.int8), np.zeros(4, np.int32))
    is_roof = np.r_[np.zeros(len(wf), bool), np.ones(len(rf), bool)]
    return data, mesh, pts, nrm, is_roof


def test_the_roof_under_a_dropped_chord_stays_and_the_offset_wall_is_still_replaced():
    data, mesh, pts, nrm, is_roof = _case()
    replaced = np.ones(len(data.zone_faces), bool)
    out, rep, counts = drop_unsupported(mesh, replaced, data, pts, nrm, DROPPED, cKDTree(pts), 0.06)
    assert counts["unsupported_faces_dropped"] == 2 and out.n_faces == 2  # the chord went, the wall stayed
    assert not rep[is_roof].any()  # every roof face under the chord is the input's again
    assert counts["input_faces_restored"] == int(is_roof.sum())
    assert rep[~is_roof].all()  # the wall, offset part and all, stays replaced: the rebuilt wall covers it

    off = RepairConfig.model_validate({"mesh": {"restore_dropped_m": 0, "restore_scope": "dropped"}}).mesh
    _, rep0, counts0 = drop_unsupported(mesh, replaced, data, pts, nrm, off, cKDTree(pts), 0.06)
    assert rep0.all() and counts0["input_faces_restored"] == 0  # the old behaviour: the roof is lost


def test_a_face_the_scan_contradicts_is_not_put_back():
    """Scan points 30 cm above the roof (a parapet the input lacks): the roof faces nearest to them are
    contradicted and stay replaced though the chord above them is dropped."""
    data, mesh, pts, nrm, is_roof = _case()
    rng = np.random.default_rng(6)
    above = np.c_[rng.uniform(1.0, 3.0, 3000), rng.uniform(0.3, 0.7, 3000), np.full(3000, 3.3)]
    pts2 = np.concatenate([pts, above])
    nrm2 = np.concatenate([nrm, np.tile([0.0, 0.0, 1.0], (len(above), 1))])
    replaced = np.ones(len(data.zone_faces), bool)
    _, rep, counts = drop_unsupported(mesh, replaced, data, pts2, nrm2, DROPPED, cKDTree(pts2), 0.06)
    c = data.xyz[data.zone_faces].mean(axis=1)
    under = is_roof & (c[:, 0] > 1.2) & (c[:, 0] < 2.8) & (c[:, 1] > 0.3) & (c[:, 1] < 0.7)
    assert under.any() and rep[under].all()
    assert 0 < counts["input_faces_restored"] < int(is_roof.sum())


def test_a_roof_the_rebuild_never_reached_comes_back_with_the_uncovered_scope():
    """No chord at all: the rebuild stops at the wall's top (the chart dropped what the scan did not show), so
    the roof strip in the zone (y 0-1; the roof beyond, y 1-2, is retained) is replaced by nothing. Scope
    "dropped" leaves it open (no chord was dropped); scope "uncovered" keeps the input roof, which continues
    the retained roof, while the offset wall stays replaced (the rebuilt wall covers it). A piece of the zone
    touching no retained face (an island inside the rebuild) is not put back."""
    from dataclasses import replace

    data, mesh, pts, nrm, is_roof = _case()
    rv, rf = _grid(0, 4, 8, 0, 2, 4, "roof")
    n_wall = int((~is_roof).sum())
    wall_v = data.xyz[: len(data.xyz) - 27]
    xyz = np.concatenate([wall_v, rv])
    yc = rv[rf].mean(axis=1)[:, 1]
    zone = np.concatenate([data.zone_faces[:n_wall], rf[yc < 1] + len(wall_v)])
    ctx = rf[yc >= 1] + len(wall_v)
    data = replace(data, xyz=xyz, vertex_id=np.arange(len(xyz)), zone_faces=zone, context_faces=ctx,
                   near_zone=np.ones(len(xyz), bool))
    is_roof = np.r_[np.zeros(n_wall, bool), np.ones(int((yc < 1).sum()), bool)]
    wall_only = RebuiltMesh(mesh.xyz[:4], mesh.vertex_id[:4], mesh.faces[:2], mesh.source[:4], mesh.chart[:2])
    replaced = np.ones(len(zone), bool)
    dropped = RepairConfig.model_validate({"mesh": {"restore_scope": "dropped"}}).mesh
    _, rep, counts = drop_unsupported(wall_only, replaced, data, pts, nrm, dropped, cKDTree(pts), 0.06)
    assert rep.all() and counts["input_faces_restored"] == 0
    uncovered = RepairConfig().mesh
    assert uncovered.restore_scope == "uncovered"  # the default
    out, rep, counts = drop_unsupported(wall_only, replaced, data, pts, nrm, uncovered, cKDTree(pts), 0.06)
    assert out.n_faces == 2 and counts["unsupported_faces_dropped"] == 0
    assert not rep[is_roof].any() and rep[~is_roof].all()
    assert counts["input_faces_restored"] == int(is_roof.sum())

    island = replace(data, context_faces=np.zeros((0, 3), np.int64))  # nothing retained around the zone
    _, rep, counts = drop_unsupported(wall_only, replaced, island, pts, nrm, uncovered, cKDTree(pts), 0.06)
    assert rep.all() and counts["input_faces_restored"] == 0
