"""The conforming splitter of long faces (tasks.geometry.split): exact checks on hand-made meshes."""

from __future__ import annotations

import numpy as np
import pytest

from storage.grid import PatchGrid
from tasks.geometry.split import split_long_faces, split_vertex_id


def _areas(tri: np.ndarray) -> np.ndarray:
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def _normals(tri: np.ndarray) -> np.ndarray:
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _wall(ids_base: int = 0):
    """A 10 m x 7 m vertical wall (plane y = 0.5) as two triangles over four shared vertices."""
    v = np.array([[0.0, 0.5, 0.0], [10.0, 0.5, 0.0], [10.0, 0.5, 7.0], [0.0, 0.5, 7.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return v, f, f.astype(np.int64) + ids_base


def _edge_table(tri: np.ndarray, ids: np.ndarray):
    """Every directed edge as (sorted id pair, its two end points in id order)."""
    rows = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        swap = ids[:, a] > ids[:, b]
        lo_i, hi_i = np.where(swap, ids[:, b], ids[:, a]), np.where(swap, ids[:, a], ids[:, b])
        lo_p = np.where(swap[:, None], tri[:, b], tri[:, a])
        hi_p = np.where(swap[:, None], tri[:, a], tri[:, b])
        rows.append((lo_i, hi_i, lo_p, hi_p))
    cat = lambda k: np.concatenate([r[k] for r in rows])
    return np.stack([cat(0), cat(1)], axis=1), cat(2), cat(3)


def test_wall_split_is_conforming_area_conserving_and_keeps_winding():
    v, f, ids = _wall()
    s = split_long_faces(v[f], ids, max_edge_m=0.7)
    assert (np.linalg.norm(s.tri - s.tri[:, [1, 2, 0]], axis=2) <= 0.7).all()
    assert _areas(s.tri).sum() == pytest.approx(70.0, rel=1e-12)
    assert np.bincount(s.parent).tolist() == [len(s.parent) // 2] * 2  # symmetric halves
    for p in (0, 1):
        assert _areas(s.tri[s.parent == p]).sum() == pytest.approx(35.0, rel=1e-12)
    assert np.allclose(_normals(s.tri), _normals(v[f])[s.parent])  # same winding as the parent
    # conforming: a closed 2-manifold with boundary; every interior edge is shared by exactly two pieces
    # and the boundary is exactly the rectangle's outline (no T-junction leaves a dangling edge)
    pairs, lo, hi = _edge_table(s.tri, s.ids)
    _, inverse, counts = np.unique(pairs, axis=0, return_inverse=True, return_counts=True)
    assert counts.max() == 2
    boundary = counts[inverse.ravel()] == 1
    mid = (lo[boundary] + hi[boundary]) / 2
    on_outline = np.isclose(mid[:, 0], 0) | np.isclose(mid[:, 0], 10) | np.isclose(mid[:, 2], 0) | np.isclose(mid[:, 2], 7)
    assert on_outline.all()
    assert np.linalg.norm(hi[boundary] - lo[boundary], axis=1).sum() == pytest.approx(34.0)
    # equal ids <=> equal positions
    all_ids, all_pts = s.ids.ravel(), s.tri.reshape(-1, 3)
    _, first, inv = np.unique(all_ids, return_index=True, return_inverse=True)
    assert np.array_equal(all_pts, all_pts[first][inv.ravel()])
    assert len(np.unique(all_pts, axis=0)) == len(first)


def test_shared_edge_gets_the_same_new_ids_from_both_faces():
    v, f, ids = _wall(ids_base=(7 << 32))
    s = split_long_faces(v[f], ids, max_edge_m=0.7)
    on_diagonal = lambda p: np.isclose(p[..., 0] * 0.7, p[..., 2])  # the shared edge (0,0)-(10,7)
    per_face = [set(s.ids[s.parent == p][on_diagonal(s.tri[s.parent == p])].tolist()) for p in (0, 1)]
    assert per_face[0] == per_face[1] and len(per_face[0]) > 2
    new = np.setdiff1d(s.ids, ids)
    assert (new <= -2).all()  # the reserved range: never an input id (>= 0) nor "no id" (-1)
    assert np.array_equal(split_vertex_id(ids[:, 0], ids[:, 1]), split_vertex_id(ids[:, 1], ids[:, 0]))


def test_every_patch_the_wall_crosses_gets_a_face():
    grid = PatchGrid((2.3, 1.0, 0.7))
    v, f, ids = _wall()
    before = np.unique(grid.pack(grid.cells_world(v[f].mean(axis=1))))
    s = split_long_faces(v[f], ids, max_edge_m=min(grid.size_m))
    got = set(grid.pack(grid.cells_world(s.tri.mean(axis=1))).tolist())
    xs, zs = np.meshgrid(np.arange(0.01, 10, 0.02), np.arange(0.01, 7, 0.02))
    dense = np.stack([xs.ravel(), np.full(xs.size, 0.5), zs.ravel()], axis=1)
    crossed = set(grid.pack(grid.cells_world(dense)).tolist())
    assert len(before) == 2 and len(crossed) == 5 * 10
    assert crossed == got


def test_uv_is_interpolated_and_small_faces_untouched():
    tri = np.array([[[0.0, 0, 0], [4, 0, 0], [0, 4, 0]], [[10.0, 0, 0], [10.3, 0, 0], [10, 0.3, 0]]])
    uv = np.array([[[0, 0], [1, 0], [0, 1]], [[0, 0], [1, 0], [0, 1]]], np.float32)
    s = split_long_faces(tri, np.arange(6).reshape(2, 3), max_edge_m=1.0, uv=uv)
    assert s.parent[0] == 1 and np.array_equal(s.tri[0], tri[1]) and (s.parent[1:] == 0).all()
    big = s.parent == 0
    assert np.allclose(s.uv[big], s.tri[big, :, :2] / 4.0, atol=1e-6)  # uv = xy / 4 on the big face
    assert s.n_split == 1


def test_skinny_triangles_converge():
    rng = np.random.default_rng(3)
    tri = rng.uniform(0, 20, (40, 3, 3))
    tri[:, 2] = tri[:, 0] + (tri[:, 1] - tri[:, 0]) * 0.5 + 0.01  # slivers
    s = split_long_faces(tri, np.arange(120).reshape(40, 3), max_edge_m=0.5)
    assert (np.linalg.norm(s.tri - s.tri[:, [1, 2, 0]], axis=2) <= 0.5).all()
    assert _areas(s.tri).sum() == pytest.approx(_areas(tri).sum(), rel=1e-9)
