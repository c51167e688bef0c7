"""The hand-made pair cues (:mod:`ms3d_model.cues`) on pairs built in code with known answers, and the
vectorised extraction equal to the per-pair loop it replaced (kept below as ``_reference_pair_cues``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from ms3d_model.cues import (
    CUE_NAMES,
    EXTRA_CUE_NAMES,
    MAX_CUE_POINTS,
    MAX_SHAPE_POINTS,
    PAIR_CUE_NAMES,
    batch_cues,
    open_edge_flags,
    pair_cues,
)
from ms3d_model.features import edge_neighbours, pair_seed, vertex_ids_from_coords
from ms3d_model.hashing import order_free_subset
from ms3d_model.kernels import closest_point_on_triangles


def grid_wall(nx: int = 8, nz: int = 4, cell_m: float = 0.25, hole: tuple[int, int] | None = None):
    """A vertical wall in the plane y = 0 (normals -y): (tris (m, 3, 3) float64, vids (m, 3)).

    Squares of ``cell_m`` over x in [0, nx * cell_m], z in [0, nz * cell_m], two triangles each, wound so the
    normal is -y (towards a scanner standing at y < 0). ``hole``: the (ix, iz) square left out."""
    tris, vids = [], []
    vid = lambda i, k: i * (nz + 1) + k
    for i in range(nx):
        for k in range(nz):
            if hole == (i, k):
                continue
            a, b, c, d = (i, k), (i + 1, k), (i + 1, k + 1), (i, k + 1)
            for tri in ((a, b, c), (a, c, d)):
                tris.append([[u * cell_m, 0.0, w * cell_m] for u, w in tri])
                vids.append([vid(*v) for v in tri])
    return np.array(tris), np.array(vids, np.int64)


def wall_points(n: int, nx: int = 8, nz: int = 4, cell_m: float = 0.25, offset_y: float = 0.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    return np.stack([rng.uniform(0, nx * cell_m, n), np.full(n, offset_y), rng.uniform(0, nz * cell_m, n)], 1)


def cue(values: np.ndarray, name: str) -> float:
    return float(values[..., CUE_NAMES.index(name)])


def test_the_wall_faces_the_scanner():
    tris, _ = grid_wall()
    normal = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    assert (normal[:, 1] < 0).all() and np.allclose(normal[:, [0, 2]], 0)


def test_points_on_the_mesh_lie_at_zero_distance_and_cover_it():
    tris, _ = grid_wall()
    c = pair_cues(wall_points(4000), tris)
    for name in ("p2m_mean", "p2m_median", "p2m_p90", "p2m_max", "p2m_signed_median", "p2m_frac_5cm"):
        assert abs(cue(c, name)) < 1e-6, name
    assert cue(c, "coverage_10cm") == pytest.approx(1.0)
    assert cue(c, "m2p_max") < 0.10
    assert cue(c, "normal_agreement") == pytest.approx(1.0, abs=1e-6)
    assert cue(c, "point_planarity") < 1e-9 and cue(c, "point_spread_along_normal") < 1e-9
    assert cue(c, "frac_horizontal_faces") == 0.0 and cue(c, "mesh_normal_spread") == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("offset_m, sign", [(-0.2, 1.0), (0.2, -1.0)])
def test_points_off_the_mesh_give_the_offset_and_its_side(offset_m, sign):
    tris, _ = grid_wall()
    c = pair_cues(wall_points(3000, offset_y=offset_m), tris)
    assert cue(c, "p2m_median") == pytest.approx(0.2, abs=1e-6)
    assert cue(c, "p2m_mean") == pytest.approx(0.2, abs=1e-6)
    assert cue(c, "p2m_frac_15cm") == 1.0 and cue(c, "p2m_frac_5cm") == 1.0
    # the normal is -y: points in front (y < 0) are on the positive side
    assert cue(c, "p2m_signed_median") == pytest.approx(sign * 0.2, abs=1e-6)
    assert cue(c, "p2m_signed_mean") == pytest.approx(sign * 0.2, abs=1e-6)
    assert cue(c, "coverage_10cm") == 0.0 and cue(c, "m2p_mean") >= 0.2 - 1e-6


@pytest.mark.parametrize("offset_m", [-0.2, 0.2, 0.05, 0.4])
def test_the_extra_cues_give_the_side_quantiles_and_reach(offset_m):
    """Points offset from the wall (normal -y): shares behind / in front beyond 10 cm, beyond 30 cm, the
    quartiles and signed percentiles equal the offset; the points reach 0.3 m above the wall's top."""
    tris, _ = grid_wall()  # 2 m wide, 1 m high, z in [0, 1]
    pts = wall_points(3000, offset_y=offset_m)
    pts = np.concatenate([pts, [[1.0, offset_m, 1.3]]])  # one point 0.3 m above the top
    c = pair_cues(pts, tris)
    front = -offset_m  # signed distance: + on the -y side
    assert cue(c, "p2m_frac_front_10cm") == pytest.approx(float(front > 0.1), abs=1e-3)
    assert cue(c, "p2m_frac_behind_10cm") == pytest.approx(float(front < -0.1), abs=1e-3)
    assert cue(c, "p2m_frac_30cm") == pytest.approx(float(abs(offset_m) > 0.3), abs=1e-3)
    for name in ("p2m_p25", "p2m_p75"):
        assert cue(c, name) == pytest.approx(abs(offset_m), abs=1e-6), name
    for name in ("p2m_signed_p10", "p2m_signed_p90"):
        assert cue(c, name) == pytest.approx(front, abs=1e-6), name
    assert cue(c, "points_above_mesh_m") == pytest.approx(0.3, abs=1e-6)
    assert cue(c, "points_below_mesh_m") < 0.01
    assert cue(c, "m2p_frac_25cm") == pytest.approx(float(abs(offset_m) > 0.25), abs=1e-6)
    assert cue(c, "m2p_median") >= abs(offset_m) - 1e-6


def test_a_hole_shows_as_open_edges_of_its_perimeter():
    cell = 0.25
    tris, vids = grid_wall(cell_m=cell, hole=(3, 2))
    full, _ = grid_wall(cell_m=cell)
    outer = 2 * (8 + 4) * cell
    # the patch is the whole wall; in the tile the wall continues (its outer edges are shared), so the
    # tile-level open edges are the hole's four sides
    tile_open = open_edge_flags(vids)
    tile_open[edge_boundary(full, tris)] = False
    pts = wall_points(3000)
    c = pair_cues(pts, tris, tile_open)
    assert cue(c, "open_edge_m") == pytest.approx(4 * cell, abs=1e-6)
    assert cue(c, "open_edge_count") == 4
    assert cue(c, "patch_boundary_m") == pytest.approx(outer + 4 * cell, abs=1e-6)
    # without tile edges the patch boundary stands in
    assert cue(pair_cues(pts, tris), "open_edge_m") == pytest.approx(outer + 4 * cell, abs=1e-6)
    # no hole: no open edge in the tile
    no_hole = np.zeros((len(full), 3), bool)
    assert cue(pair_cues(pts, full, no_hole), "open_edge_m") == 0.0
    assert cue(pair_cues(pts, full), "patch_boundary_m") == pytest.approx(outer, abs=1e-6)


def test_open_edge_flags_equal_the_edge_neighbours_definition_on_random_and_degenerate_faces():
    """The lean whole-tile version (one sort, no face tiebreak key) against its definition, on random
    small vertex sets: shared, boundary, repeated and degenerate (a vertex twice in a face) edges."""
    rng = np.random.default_rng(1)
    seen_open = seen_shared = 0
    for _ in range(300):
        m = int(rng.integers(1, 60))
        vids = rng.integers(0, int(rng.integers(2, 30)), (m, 3))
        got = open_edge_flags(vids)
        assert np.array_equal(got, edge_neighbours(vids) == np.arange(m)[:, None]), vids
        seen_open, seen_shared = seen_open + got.sum(), seen_shared + (~got).sum()
    assert seen_open > 100 and seen_shared > 100  # both kinds were exercised


def edge_boundary(full: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(m, 3) bool: edges of ``tris`` on the outer boundary of the complete wall ``full``."""
    on_x = lambda v: np.isclose(v[..., 0], 0) | np.isclose(v[..., 0], full[..., 0].max())
    on_z = lambda v: np.isclose(v[..., 2], 0) | np.isclose(v[..., 2], full[..., 2].max())
    a, b = tris, np.roll(tris, -1, axis=1)
    return (on_x(a) & on_x(b) & np.isclose(a[..., 0], b[..., 0])) | (on_z(a) & on_z(b) & np.isclose(a[..., 2], b[..., 2]))


def test_counts_and_area():
    tris, _ = grid_wall(nx=8, nz=4, cell_m=0.25)
    c = pair_cues(wall_points(500), tris)
    assert cue(c, "log_n_points") == pytest.approx(np.log1p(500))
    assert cue(c, "log_n_faces") == pytest.approx(np.log1p(64))
    assert cue(c, "mesh_area_m2") == pytest.approx(2.0)
    assert cue(c, "log_point_density") == pytest.approx(np.log1p(250.0))


def test_a_roof_counts_as_horizontal():
    tris, _ = grid_wall()
    roof = tris[:, :, [0, 2, 1]] * [1, 1, 1]  # the wall laid flat: z = 0
    c = pair_cues(wall_points(500)[:, [0, 2, 1]], roof)
    assert cue(c, "frac_horizontal_faces") == pytest.approx(1.0)


# -- the vectorised extraction equals the per-pair loop it replaced --------------------------------------

def _reference_pair_cues(points, tris, open_edges=None, seed=0) -> np.ndarray:
    """The per-pair implementation before vectorisation (ms3d_model/cues.py before commit 01223df), verbatim
    maths; its closest_point_on_triangles is ms3d_model.kernels', which no longer gives NaN on a zero-area face."""
    p_all = np.asarray(points, np.float64).reshape(-1, 3)
    t = np.asarray(tris, np.float64).reshape(-1, 3, 3)
    n, m = len(p_all), len(t)
    p = p_all[order_free_subset(p_all, MAX_CUE_POINTS, seed)] if n > MAX_CUE_POINTS else p_all  # row-order free
    cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    area2 = np.linalg.norm(cross, axis=1)
    area = 0.5 * area2
    normals = np.divide(cross, area2[:, None], out=np.zeros_like(cross), where=area2[:, None] > 0)
    centres = t.mean(axis=1)
    total_area = float(area.sum())
    k = min(8, m)
    _, fi = cKDTree(centres).query(p, k=k)
    fi = np.asarray(fi).reshape(len(p), k)
    q = closest_point_on_triangles(np.repeat(p, k, axis=0), t[fi.ravel()]).reshape(len(p), k, 3)
    dist = np.linalg.norm(q - p[:, None], axis=2)
    best = dist.argmin(axis=1)
    d = dist[np.arange(len(p)), best]
    fbest = fi[np.arange(len(p)), best]
    signed = np.sign(((p - q[np.arange(len(p)), best]) * normals[fbest]).sum(1)) * d
    dm, _ = cKDTree(p_all).query(centres, k=1)
    w = area / total_area if total_area > 0 else np.full(m, 1.0 / m)
    nb = edge_neighbours(vertex_ids_from_coords(t.astype(np.float32)))
    edge_len = np.linalg.norm(np.roll(t, -1, axis=1) - t, axis=2)
    patch_open = nb == np.arange(m)[:, None]
    tile_open = patch_open if open_edges is None else np.asarray(open_edges, bool)
    mean_n = (normals * area[:, None]).sum(0)
    mean_len = np.linalg.norm(mean_n)
    mesh_n = mean_n / mean_len if mean_len > 0 else np.array([0.0, 0.0, 1.0])
    if n >= 3:
        ev, evec = np.linalg.eigh(np.cov(p_all.T))
        pt_n, planarity = evec[:, 0], float(max(ev[0], 0.0) / max(ev.sum(), 1e-12))
    else:
        pt_n, planarity = mesh_n, 0.0
    along_p, along_m = p_all @ mesh_n, t.reshape(-1, 3) @ mesh_n
    return np.asarray([
        np.log1p(n), np.log1p(m), total_area, np.log1p(n / max(total_area, 1e-3)),
        d.mean(), np.median(d), np.percentile(d, 90), d.max(), (d > 0.05).mean(), (d > 0.15).mean(),
        np.median(signed), signed.mean(),
        dm.mean(), np.percentile(dm, 90), dm.max(), float(w[dm <= 0.10].sum()),
        float(edge_len[patch_open].sum()), float(edge_len[tile_open].sum()), float(tile_open.sum()),
        abs(float(pt_n @ mesh_n)), planarity, 1.0 - mean_len / max(total_area, 1e-12),
        np.percentile(along_p, 90) - np.percentile(along_p, 10), np.percentile(along_m, 90) - np.percentile(along_m, 10),
        float(w[np.abs(normals[:, 2]) > 0.9].sum())], np.float32)


def mixed_pairs(seed: int = 3):
    """Pairs of every shape the loop had to handle: big (subsampled) and tiny point sets, fewer than 8 faces,
    a single face, a degenerate face, two points, tilted and noisy meshes, far-apart pairs (campus-local)."""
    rng = np.random.default_rng(seed)
    pairs = []
    for b in range(14):
        nx, nz = int(rng.integers(1, 7)), int(rng.integers(1, 4))
        tris, _ = grid_wall(nx, nz, cell_m=float(rng.uniform(0.1, 0.4)))
        tris = tris + rng.normal(0, 0.02, tris.shape)  # an MVS-like crumpled surface (welded ids are lost)
        tris = np.where(rng.random(tris.shape[:1])[:, None, None] < 0.1, tris[:, [0, 0, 1]], tris)  # degenerate
        n = [2, 5, 40, 700, 1500, 3000][b % 6]
        pts = wall_points(n, nx, nz, float(tris[..., 0].max() / max(nx, 1)), offset_y=float(rng.normal(0, 0.1)),
                          seed=b) + rng.normal(0, 0.03, (n, 3))
        angle = rng.uniform(0, np.pi)
        rot = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        shift = rng.uniform(-1500, 1500, 3)
        oe = rng.random((len(tris), 3)) < 0.2
        pairs.append((pts @ rot.T + shift, tris @ rot.T + shift, oe))
    return pairs


def test_batched_cues_equal_the_per_pair_loop():
    pairs = mixed_pairs()
    keys = np.arange(len(pairs), dtype=np.int64) * 7919 + 11
    got = batch_cues([p for p, _, _ in pairs], [t for _, t, _ in pairs], [o for _, _, o in pairs], keys, seed=5)
    want = np.stack([_reference_pair_cues(p, t, o, pair_seed(5, int(k))) for (p, t, o), k in zip(pairs, keys)])
    n_ref = len(PAIR_CUE_NAMES) - len(EXTRA_CUE_NAMES)  # the loop predates the extra cues
    np.testing.assert_allclose(got[:, :n_ref], want, rtol=1e-6, atol=1e-6)
    # one pair at a time gives the same as in a batch, and the patch boundary stands in without tile edges
    p, t, _ = pairs[4]
    np.testing.assert_allclose(pair_cues(p, t, seed=9)[:n_ref], _reference_pair_cues(p, t, None, 9), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(batch_cues([p], [t], None, keys[4:5], seed=5)[0],
                                  batch_cues([pairs[0][0], p], [pairs[0][1], t], None, keys[[0, 4]], seed=5)[1])


def test_a_pair_above_the_shape_cap_keeps_its_count_and_extent_and_its_shape_cues(monkeypatch):
    """Real MLS density: the whole-point-set cues of a pair above MAX_SHAPE_POINTS use a seeded subsample of
    that many points. The count and the z extent still see every point, the shape cues stay within noise of
    the uncapped ones, and a pair at the cap is computed on all its points, as before."""
    import ms3d_model.cues as cues_mod

    tris, _ = grid_wall(8, 4)
    rng = np.random.default_rng(4)
    n = 3 * MAX_SHAPE_POINTS
    pts = wall_points(n, seed=2) + rng.normal(0, 0.01, (n, 3))
    pts[-1] = [1.0, -0.05, 1.6]  # one point 0.6 m above the wall top: the subsample would likely miss it
    capped = pair_cues(pts, tris, seed=7)
    monkeypatch.setattr(cues_mod, "MAX_SHAPE_POINTS", 10 * n)
    full = pair_cues(pts, tris, seed=7)
    assert cue(capped, "log_n_points") == cue(full, "log_n_points") == pytest.approx(np.log1p(n))
    assert cue(capped, "points_above_mesh_m") == cue(full, "points_above_mesh_m") == pytest.approx(0.6, abs=1e-6)
    for name, tol in (("coverage_10cm", 1e-6), ("point_planarity", 1e-4), ("normal_agreement", 1e-4),
                      ("point_spread_along_normal", 2e-3), ("m2p_mean", 5e-3)):
        assert cue(capped, name) == pytest.approx(cue(full, name), abs=tol), name
    assert not np.array_equal(capped, full)  # the cap did apply
    monkeypatch.setattr(cues_mod, "MAX_SHAPE_POINTS", n)  # at the cap: every point, the uncapped cues
    np.testing.assert_array_equal(pair_cues(pts, tris, seed=7), full)


def test_the_cues_do_not_depend_on_the_order_of_the_points():
    """A patch's rows arrive in the order of their input runs, i.e. of the inputs' paths: a renamed input (a
    local path uploaded to S3) must grade alike. Above both subsampling caps the cues of shuffled rows equal
    the original's to rounding (a row-position subsample differs by millimetres)."""
    tris, _ = grid_wall(8, 4)
    n = 2 * MAX_SHAPE_POINTS
    pts = wall_points(n, seed=3) + np.random.default_rng(5).normal(0, 0.02, (n, 3))
    perm = np.random.default_rng(6).permutation(n)
    a, b = pair_cues(pts, tris, seed=11), pair_cues(pts[perm], tris, seed=11)
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
    assert cue(a, "p2m_mean") != cue(pair_cues(pts, tris, seed=12), "p2m_mean")  # the subsample is in play


def test_a_pair_without_points_or_faces_is_refused():
    tris, _ = grid_wall(1, 1)
    with pytest.raises(ValueError, match="at least one point and one face"):
        batch_cues([np.zeros((0, 3))], [tris], None, np.array([1]))


def test_a_degenerate_face_gives_finite_cues():
    """Intended change: the loop gave NaN distances (0 / 0 in the triangle test) for a zero-area face."""
    tris, _ = grid_wall(2, 1)
    sliver = np.array([[[0.0, -0.5, 0.0], [0.0, -0.5, 0.0], [0.5, -0.5, 0.0]]])  # a segment 0.5 m in front
    pts = np.array([[0.2, -0.45, 0.0], [0.3, 0.0, 0.1], [0.1, 0.0, 0.2]])
    c = pair_cues(pts, np.concatenate([tris, sliver]))
    assert np.isfinite(c).all()
    assert cue(c, "p2m_max") == pytest.approx(0.05, abs=1e-6)
    q = closest_point_on_triangles(pts[:1], sliver)
    np.testing.assert_allclose(q, [[0.2, -0.5, 0.0]])
