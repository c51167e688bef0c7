"""Featurisation of hand-made patches: exact centres, normals, corners, neighbours; FPS; fixed sizes."""

from __future__ import annotations

import numpy as np
import pytest

from ms3d_model.features import (
    edge_neighbours,
    face_geometry,
    featurise_pairs,
    fix_size,
    fps_indices,
    knn_indices,
    normalise_pair,
)

# Two triangles of a unit square in z = 0, sharing the edge v1-v2 (vertex ids 11, 12):
#   A = (v0, v1, v2), B = (v1, v3, v2)
V = np.array([[-1, -1, 0], [1, -1, 0], [-1, 1, 0], [1, 1, 0]], np.float32)
TRIS = V[[[0, 1, 2], [1, 3, 2]]]
VIDS = np.array([[10, 11, 12], [11, 13, 12]])


def test_two_triangles_exact_features():
    c, n, k = face_geometry(TRIS)
    np.testing.assert_allclose(c, [[-1 / 3, -1 / 3, 0], [1 / 3, 1 / 3, 0]], atol=1e-7)
    np.testing.assert_array_equal(n, [[0, 0, 1], [0, 0, 1]])
    # corner i = (v[i+1] - v[i], v[i+2] - v[i]); face A = ((-1,-1), (1,-1), (-1,1))
    np.testing.assert_array_equal(k[0], [2, 0, 0, 0, 2, 0,      # corner 0: v1 - v0, v2 - v0
                                         -2, 2, 0, -2, 0, 0,    # corner 1: v2 - v1, v0 - v1
                                         0, -2, 0, 2, -2, 0])   # corner 2: v0 - v2, v1 - v2
    # neighbour j lies across edge (v_j, v_{j+1}); A's edge 1 is v1-v2, B's edge 2 is v2-v1; others: self
    np.testing.assert_array_equal(edge_neighbours(VIDS), [[0, 1, 0], [1, 1, 0]])


def test_two_triangle_pair_end_to_end():
    # points span z in [-1, 1] so the pair's joint box is [-1, 1]^3: the normalisation is the identity
    pts = np.array([[0, 0, -1], [0, 0, 1], [0.5, 0.5, 0]], np.float32)
    f = featurise_pairs([pts], [TRIS], [VIDS], np.array([7]), max_points=3, max_faces=2, k_centre=1)
    assert f.scale.tolist() == [1.0]
    np.testing.assert_array_equal(np.sort(f.points[0], axis=0), np.sort(pts, axis=0))
    np.testing.assert_allclose(f.centres[0], [[-1 / 3, -1 / 3, 0], [1 / 3, 1 / 3, 0]], atol=1e-7)
    np.testing.assert_array_equal(f.normals[0], [[0, 0, 1], [0, 0, 1]])
    np.testing.assert_array_equal(f.face_nbr[0], [[0, 1, 0], [1, 1, 0]])
    np.testing.assert_array_equal(f.centre_knn[0], [[1], [0]])
    assert f.n_faces.tolist() == [2] and f.n_points.tolist() == [3]


def test_edge_neighbours_respect_pairs_and_non_manifold_edges():
    # the same two faces in two pairs never see each other across pairs
    vids = np.concatenate([VIDS, VIDS])
    np.testing.assert_array_equal(edge_neighbours(vids, np.array([0, 0, 1, 1])),
                                  [[0, 1, 0], [1, 1, 0], [2, 3, 2], [3, 3, 2]])
    # three faces on one edge (11, 12): each points to the next one sharing it, cyclically
    fan = np.array([[11, 12, 20], [12, 11, 21], [11, 12, 22]])
    assert edge_neighbours(fan)[:, 0].tolist() == [1, 2, 0]


def test_padding_repeats_faces_with_their_neighbour_rows():
    pts = np.zeros((5, 3), np.float32) + [[0, 0, -1]]
    f = featurise_pairs([pts], [TRIS], [VIDS], np.array([3]), max_points=8, max_faces=6, k_centre=1, seed=4)
    assert f.centres.shape == (1, 6, 3) and f.points.shape == (1, 8, 3)
    own = f.face_nbr[0]
    assert own.max() < 2  # every index points into the two real faces
    for r in range(6):  # a repeated face carries the row of the face it repeats
        src = 0 if np.allclose(f.centres[0, r], f.centres[0, 0]) else 1
        np.testing.assert_array_equal(own[r], [[0, 1, 0], [1, 1, 0]][src])


def test_downsampling_remaps_neighbours_to_kept_faces():
    # a 10 x 10 grid of squares (200 triangles) with shared vertex ids, sampled down to 120 faces
    g = np.arange(11)
    vid = g[:, None] * 11 + g[None, :]
    xy = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2).astype(np.float32)
    a, b, c, d = vid[:-1, :-1].ravel(), vid[1:, :-1].ravel(), vid[:-1, 1:].ravel(), vid[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([b, d, c], 1)])
    tris = np.concatenate([xy, np.zeros((121, 1), np.float32)], 1)[faces]
    pts = np.array([[0, 0, -5], [10, 10, 5]], np.float32)
    f = featurise_pairs([pts], [tris], [faces], np.array([1]), 8, 120, 4)
    centre, scale = normalise_pair(pts, tris)
    orig_c = (tris.mean(1) - centre) / scale
    kept = np.array([np.argmin(np.linalg.norm(orig_c - r, axis=1)) for r in f.centres[0]])
    assert len(np.unique(kept)) == 120
    full = edge_neighbours(faces)
    for i in range(120):
        for e in range(3):
            o = full[kept[i], e]  # the original neighbour across edge e
            want = int(np.flatnonzero(kept == o)[0]) if o != kept[i] and o in kept else i
            assert f.face_nbr[0, i, e] == want


def test_fps_keeps_count_and_is_deterministic():
    xyz = np.random.default_rng(1).normal(size=(3000, 3)).astype(np.float32)
    a, b = fps_indices(xyz, 500, seed=3), fps_indices(xyz, 500, seed=3)
    assert len(a) == 500 and len(np.unique(a)) == 500
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, fps_indices(xyz, 500, seed=4))
    up = fix_size(xyz[:10], 25, seed=0)
    assert len(up) == 25 and set(up[:10].tolist()) == set(range(10)) and up.max() < 10
    np.testing.assert_array_equal(up, fix_size(xyz[:10], 25, seed=0))


def test_knn_excludes_self_and_pads_small_sets():
    c = np.array([[0, 0, 0], [1, 0, 0], [3, 0, 0]], np.float32)
    assert knn_indices(c, 1).tolist() == [[1], [0], [1]]
    assert knn_indices(c, 3).tolist() == [[1, 2, 0], [0, 2, 1], [1, 0, 2]]


def test_normalise_pair_puts_both_in_unit_box_with_one_transform():
    pts = np.array([[10, 0, 0], [12, 0, 0]], np.float64)
    tris = np.array([[[10, 1, 0], [11, 1, 0], [10, 2, 0]]], np.float64)
    centre, scale = normalise_pair(pts, tris)
    np.testing.assert_allclose(centre, [11, 1, 0])
    assert scale == pytest.approx(1.0)
