"""Triangulation of fused points (§5.2): charts, box areas, seams, stitching."""

import numpy as np
import pytest

from tasks.geometry.triangles import face_areas
from tasks.repair.chart import boundary_edges, disc_parameterisation, split_fans, trace_loops, zone_charts
from tasks.repair.mesh import border_gap, poisson_surface, rebuild_charts


def _grid_box(n: int = 4, closed: bool = False):
    """A unit box as a welded triangle mesh, each side an n x n grid; without the bottom unless closed."""
    verts, index = [], {}

    def vid(p):
        key = tuple(np.round(p, 9))
        if key not in index:
            index[key] = len(verts)
            verts.append(p)
        return index[key]

    faces = []
    sides = [((0, 0, 1), (1, 0, 0), (0, 1, 0)), ((0, 0, 0), (0, 1, 0), (0, 0, 1)), ((1, 0, 0), (0, 0, 1), (0, 1, 0)),
             ((0, 0, 0), (0, 0, 1), (1, 0, 0)), ((0, 1, 0), (1, 0, 0), (0, 0, 1))]
    if closed:
        sides.append(((0, 0, 0), (1, 0, 0), (0, 1, 0)))
    for o, a, b in sides:  # o + s a + t b
        o, a, b = map(np.array, (o, a, b))
        g = [[vid(o + (i / n) * a + (j / n) * b) for j in range(n + 1)] for i in range(n + 1)]
        for i in range(n):
            for j in range(n):
                faces += [[g[i][j], g[i + 1][j], g[i + 1][j + 1]], [g[i][j], g[i + 1][j + 1], g[i][j + 1]]]
    v, f = np.array(verts, float), np.array(faces)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inward = np.einsum("ij,ij->i", n, v[f].mean(1) - 0.5) < 0
    f[inward] = f[inward][:, ::-1]
    return v, f


def _box_samples(step: float, bottom: bool):
    g = np.arange(step / 2, 1, step)
    a, b = (x.ravel() for x in np.meshgrid(g, g))
    z0, o = np.zeros_like(a), np.ones_like(a)
    sides = [np.c_[a, b, o], np.c_[z0, a, b], np.c_[o, a, b], np.c_[a, z0, b], np.c_[a, o, b]]
    normals = [(0, 0, 1), (-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0)]
    if bottom:
        sides.append(np.c_[a, b, z0])
        normals.append((0, 0, -1))
    pts = np.concatenate(sides)
    nrm = np.concatenate([np.tile(n, (len(a), 1)) for n in normals]).astype(float)
    return pts, nrm


def test_box_grid_is_outward_and_welded():
    v, f = _grid_box(4)
    assert len(boundary_edges(f, len(v))) == 16  # the open bottom rim only
    c = v[f].mean(1)
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    assert (np.einsum("ij,ij->i", n, c - 0.5) > 0).all()


def test_delaunay_in_chart_recovers_the_open_box_area():
    v, f = _grid_box(4)
    topo = zone_charts(v, f, np.zeros((0, 3), int), np.zeros(len(v), bool), max_hole_loop_m=1.0)
    assert len(topo.charts) == 1 and len(topo.rejected) == 0
    pts, _ = _box_samples(0.02, bottom=False)
    m = rebuild_charts(topo.charts, np.arange(len(v)), pts, np.ones(len(pts), np.int8), np.full(len(pts), -1),
                       max_map_distance_m=0.5, border_margin_m=0.01, max_edge_m=0.3)
    area = face_areas(m.xyz, m.faces, np.float64).sum()
    assert area == pytest.approx(5.0, rel=0.02)
    rim = boundary_edges(m.faces, len(m.xyz))
    assert set(m.vertex_id[rim.ravel()]) <= set(range(len(v))) and len(rim) == 16  # the rim is the zone's own


def test_poisson_recovers_the_closed_box_area():
    pts, nrm = _box_samples(0.02, bottom=True)
    v, f, _ = poisson_surface(pts, nrm, depth=7, trim_quantile=0.0)
    assert face_areas(v, f, np.float64).sum() == pytest.approx(6.0, rel=0.02)


def test_disc_parameterisation_is_an_embedding():
    v, f = _grid_box(3)
    loops, clean = trace_loops(boundary_edges(f, len(v)))
    uv = disc_parameterisation(v, f, loops[0])
    a, b, c = uv[f[:, 0]], uv[f[:, 1]], uv[f[:, 2]]
    cross = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    assert clean and (cross > 0).all()  # every face counter-clockwise: no fold


def test_band_with_two_loops_is_cut_into_one_disc():
    v, f = _grid_box(4)  # drop the top: the four sides form a band with two boundary loops
    top = np.all(v[f][:, :, 2] > 0.999, axis=1)
    f = f[~top]
    topo = zone_charts(v, f, np.zeros((0, 3), int), np.zeros(len(v), bool), max_hole_loop_m=1.0)
    assert len(topo.charts) == 1 and topo.seams == 1 and len(topo.rejected) == 0
    pts, _ = _box_samples(0.05, bottom=False)
    pts = pts[pts[:, 2] < 0.999]
    m = rebuild_charts(topo.charts, np.arange(len(v)), pts, np.ones(len(pts), np.int8), np.full(len(pts), -1),
                       max_map_distance_m=0.5, border_margin_m=0.01, max_edge_m=0.3)
    assert face_areas(m.xyz, m.faces, np.float64).sum() == pytest.approx(4.0, rel=0.02)
    # welded back along the seam: the only open edges are the two rims (16 each)
    assert len(boundary_edges(m.faces, len(m.xyz))) == 32


def test_pinched_fans_are_split():
    # two triangles touching at vertex 0 only
    f = np.array([[0, 1, 2], [0, 3, 4]])
    _g, orig = split_fans(f, 5)
    assert len(orig) == 6 and (orig == 0).sum() == 2


def test_border_gap_is_zero_when_welded_and_measured_otherwise():
    v, f = _grid_box(2)
    zone = f[np.all(v[f][:, :, 2] > 0.999, axis=1)]  # the top
    ctx = f[~np.all(v[f][:, :, 2] > 0.999, axis=1)]
    topo = zone_charts(v, zone, ctx, np.ones(len(v), bool), max_hole_loop_m=1.0)
    pts = np.c_[np.random.default_rng(0).uniform(0.05, 0.95, (200, 2)), np.ones(200)]
    m = rebuild_charts(topo.charts, np.arange(len(v)), pts, np.ones(200, np.int8), np.full(200, -1),
                       max_map_distance_m=0.5, border_margin_m=0.01, max_edge_m=0.5)
    from tasks.repair.mesh import border_edges

    be = border_edges(zone, ctx, len(v))
    gap = border_gap(v[be], be, m)
    assert gap["border_edges"] == 8 and gap["welded"] == 8 and gap["max_gap_m"] == 0.0 and gap["open_edges"] == 0
    lifted = type(m)(m.xyz + [0, 0, 0.03], m.vertex_id + 100, m.faces, m.source, m.chart)
    assert border_gap(v[be], be, lifted)["max_gap_m"] == pytest.approx(0.03, abs=1e-3)


def test_closed_surface_is_cut_open_and_rebuilt():
    v, f = _grid_box(3, closed=True)
    assert len(boundary_edges(f, len(v))) == 0
    topo = zone_charts(v, f, np.zeros((0, 3), int), np.zeros(len(v), bool), max_hole_loop_m=1.0)
    assert len(topo.charts) == 1 and topo.seams == 1 and len(topo.rejected) == 0
    pts, _ = _box_samples(0.04, bottom=True)
    m = rebuild_charts(topo.charts, np.arange(len(v)), pts, np.ones(len(pts), np.int8), np.full(len(pts), -1),
                       max_map_distance_m=0.5, border_margin_m=0.01, max_edge_m=0.3)
    assert len(boundary_edges(m.faces, len(m.xyz))) == 0  # closed again once the cut is welded back
    assert face_areas(m.xyz, m.faces, np.float64).sum() == pytest.approx(6.0, rel=0.03)
