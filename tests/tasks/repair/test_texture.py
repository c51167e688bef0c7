"""Projective texture mapping (§5.3): view selection by angle, distance and visibility; seams; atlas."""

import numpy as np

from synth.cameras import look_rotation
from tasks.config.repair import TextureConfig
from tasks.repair.mincut import min_cut
from tasks.repair.texture import (
    NO_VIEW,
    CameraView,
    cameras_to_frame,
    select_views,
    texture_mesh,
    view_quality,
    voxel_boxes,
)
from tasks.repair.views import select_views_sparse

K = np.array([[500.0, 0, 499.5], [0, 500.0, 499.5], [0, 0, 1]])


def camera_at(centre, target, name):
    d = np.asarray(target, float) - centre
    r = look_rotation(np.arctan2(d[1], d[0]), np.arctan2(d[2], np.hypot(d[0], d[1])))
    return CameraView(name, K, r, -r @ np.asarray(centre, float), 1000, 1000)


def wall_quads(*centres):
    """1 x 1 m squares in planes x = const, facing +x, two triangles each."""
    v, f = [], []
    for c in centres:
        c = np.asarray(c, float)
        b = len(v)
        v += [c + [0, -0.5, -0.5], c + [0, 0.5, -0.5], c + [0, 0.5, 0.5], c + [0, -0.5, 0.5]]
        f += [[b, b + 1, b + 2], [b, b + 2, b + 3]]
    return np.array(v), np.array(f)


def images(*colours):
    return lambda i: np.full((1000, 1000, 3), colours[i], np.uint8)


def test_frontal_view_beats_oblique_one():
    v, f = wall_quads([0, 0, 1.5])
    frontal = camera_at(np.array([6.0, 0.0, 1.5]), [0, 0, 1.5], "frontal")
    oblique = camera_at(np.array([3.0, 5.196, 1.5]), [0, 0, 1.5], "oblique")  # 60 deg off the normal, same 6 m
    atlas, st = texture_mesh(v, f, [oblique, frontal], images((0, 255, 0), (255, 0, 0)), (np.zeros((0, 3)),
                             np.zeros((0, 3), int)), TextureConfig(), np.zeros((2, 3), np.uint8))
    assert atlas.view.tolist() == [1, 1] and st["occluded"] == 0
    # the atlas holds the frontal (red) image where the faces map
    h, w = atlas.image.shape[:2]
    uv = atlas.uv.reshape(-1, 2)
    px = atlas.image[((1 - uv[:, 1]) * h).astype(int).clip(0, h - 1), (uv[:, 0] * w).astype(int).clip(0, w - 1)]
    assert (px == [255, 0, 0]).all()


def test_face_hidden_behind_an_occluder_takes_no_view():
    v, f = wall_quads([0, 0, 1.5], [0, 3, 1.5])
    cams = [camera_at(np.array([6.0, 0.0, 1.5]), [0, 0, 1.5], "a"),
            camera_at(np.array([6.0, 2.0, 1.5]), [0, 3, 1.5], "b")]
    # a 'car' of voxels right in front of the second square hides it from both cameras
    g = np.arange(-0.9, 0.91, 0.2)
    centres = np.array([[x, y, z] for x in (0.6, 0.8) for y in 3 + g for z in 1.5 + g])
    ov, of = voxel_boxes(centres, 0.2)
    atlas, _st = texture_mesh(v, f, cams, images((255, 0, 0), (0, 0, 255)), (ov, of), TextureConfig(),
                             np.zeros((4, 3), np.uint8))
    assert (atlas.view[:2] != NO_VIEW).all() and (atlas.view[2:] == NO_VIEW).all()
    assert np.isnan(atlas.uv[2:]).all() and np.isfinite(atlas.uv[:2]).all()


def test_seam_term_removes_flicker():
    rng = np.random.default_rng(0)
    m = 200
    cost = np.full((m, 3), np.inf)
    x = np.arange(m) / m
    cost[:, 0] = 0.3 + 0.2 * (x > 0.5) + rng.uniform(0, 0.3, m)
    cost[:, 1] = 0.3 + 0.2 * (x <= 0.5) + rng.uniform(0, 0.3, m)
    adj = np.c_[np.arange(m - 1), np.arange(1, m)]
    assert (select_views(cost, adj, 0.0)[:-1] != select_views(cost, adj, 0.0)[1:]).sum() > 20
    lab = select_views(cost, adj, 0.5)
    assert (lab[:-1] != lab[1:]).sum() == 1 and lab[0] == 0 and lab[-1] == 1


def test_cameras_follow_the_registration():
    cam = camera_at(np.array([5.0, 1.0, 2.0]), [0, 0, 1], "x")
    cam = CameraView("x.jpg", K, cam.R, cam.t, 1000, 1000, np.array([-0.1, 0.02, 0.001, -0.002, 0.003]))
    m = np.eye(4)
    c, s = np.cos(0.3), np.sin(0.3)
    m[:3, :3] = 1.01 * np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    m[:3, 3] = [10.0, -4.0, 0.5]
    moved = cameras_to_frame([cam], m, "imgs")[0]
    p = np.array([[0.3, 0.2, 1.1], [-1.0, 0.5, 2.0]])
    p2 = p @ m[:3, :3].T + m[:3, 3]
    np.testing.assert_allclose(moved.project(p2)[0], cam.project(p)[0], atol=1e-6)
    assert moved.image == "imgs/x.jpg" and (moved.dist == cam.dist).all()


def _reference_select_views(cost, adjacency, w, cycles=3):
    """Alpha-expansion with every face a graph node (what select_views did before its moves were cut
    down to the faces that may switch)."""
    m, nl = cost.shape
    c = np.where(np.isfinite(cost), cost, 1e9)
    lab = np.argmin(c, axis=1)
    a, b = adjacency[:, 0], adjacency[:, 1]
    energy = lambda lb: c[np.arange(m), lb].sum() + w[lb[a] != lb[b]].sum()
    best = energy(lab)
    for _ in range(cycles):
        improved = False
        for alpha in [x for x in range(nl) if np.isfinite(cost[:, x]).any()]:
            la, lb = lab[a], lab[b]
            e00, e01, e10 = w * (la != lb), w * (la != alpha), w * (lb != alpha)
            un1 = c[:, alpha] - c[np.arange(m), lab]
            np.add.at(un1, a, e10 - e00)
            np.add.at(un1, b, -e10)
            _, sink = min_cut(np.maximum(un1, 0), np.maximum(-un1, 0), a, b, np.maximum(e01 + e10 - e00, 0),
                              np.zeros(len(a)))
            new = np.where(sink, alpha, lab)
            if energy(new) < best - 1e-9:
                best, lab, improved = energy(new), new, True
        if not improved:
            break
    return lab, best


def test_expansion_moves_on_the_faces_that_may_switch_reach_the_whole_graph_energy():
    """Random grids of faces, labels allowed on about half of them, random seam weights: the moves built
    only over the faces that may take a label reach the same energy as moves over every face."""
    rng = np.random.default_rng(0)
    n = 16
    ii = np.arange(n * n).reshape(n, n)
    adj = np.concatenate([np.c_[ii[:, :-1].ravel(), ii[:, 1:].ravel()], np.c_[ii[:-1].ravel(), ii[1:].ravel()]])
    changed = 0
    for _ in range(60):
        nl = int(rng.integers(2, 7))
        cost = rng.random((n * n, nl)) * 3
        cost[rng.random(cost.shape) < 0.5] = np.inf
        cost[:, -1] = 4.0  # the 'no view' label: always allowed
        w = rng.random(len(adj)) * float(rng.choice([0.3, 1.0, 3.0]))
        lab = select_views(cost, adj, w)
        _, e_ref = _reference_select_views(cost, adj, w)
        c = np.where(np.isfinite(cost), cost, 1e9)
        e = c[np.arange(n * n), lab].sum() + w[lab[adj[:, 0]] != lab[adj[:, 1]]].sum()
        assert np.isfinite(cost[np.arange(n * n), lab]).all()
        assert e == np.float64(e_ref) or abs(e - e_ref) < 1e-9 * max(1.0, e_ref)
        changed += int((lab != np.argmin(c, axis=1)).any())
    assert changed > 30  # the seams mattered: the moves did something in most cases


def test_view_candidates_are_the_faces_each_camera_sees_whole_and_near():
    """The sparse candidates equal a check of every (face, camera) pair: in front, within the angle and the
    distance, all three corners inside the image (2 px margin)."""
    rng = np.random.default_rng(3)
    v, f = wall_quads(*[[0, y, z] for y in np.arange(-4, 5, 1.0) for z in (0.5, 1.5, 2.5)])
    v = v + rng.normal(0, 0.05, v.shape)
    cams = [camera_at(np.array([float(x), float(y), 1.6]), [0, float(y + dy), 1.5], f"c{i}")
            for i, (x, y, dy) in enumerate([(6, 0, 0), (3, -3, 2), (12, 4, -1), (2, 6, -6), (-5, 0, 0), (25, 0, 0)])]
    fi, ci, q = view_quality(v, f, cams, max_angle_deg=70.0, max_distance_m=20.0)
    tri = v[f]
    cen = tri.mean(axis=1)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1)[:, None]
    want = {}
    for j, cam in enumerate(cams):
        for i in range(len(f)):
            d = cam.centre - cen[i]
            cos = d @ n[i] / np.linalg.norm(d)
            uv, z = cam.project(tri[i])
            inside = (z > 0.1).all() and (uv >= 2).all() and (uv[:, 0] <= 997).all() and (uv[:, 1] <= 997).all()
            if cos >= np.cos(np.radians(70.0)) and np.linalg.norm(d) <= 20.0 and inside:
                want[(i, j)] = cos * (500.0 / np.linalg.norm(d)) ** 2
    assert 20 < len(want) < len(f) * len(cams) - 20  # some pairs in, some out
    assert list(zip(fi.tolist(), ci.tolist())) == sorted(want)  # by face, then camera
    np.testing.assert_allclose(q, [want[k] for k in sorted(want)], rtol=1e-12)


def test_sparse_view_selection_takes_entries_in_any_order_and_needs_a_label_per_face():
    rng = np.random.default_rng(5)
    n = 12
    ii = np.arange(n * n).reshape(n, n)
    adj = np.concatenate([np.c_[ii[:, :-1].ravel(), ii[:, 1:].ravel()], np.c_[ii[:-1].ravel(), ii[1:].ravel()]])
    cost = rng.random((n * n, 5)) * 3
    cost[rng.random(cost.shape) < 0.6] = np.inf
    cost[:, -1] = 4.0
    face, label = np.nonzero(np.isfinite(cost))
    order = rng.permutation(len(face))
    lab = select_views_sparse(n * n, face[order], label[order], cost[face, label][order], adj, 0.8)
    assert (lab == select_views(cost, adj, 0.8)).all() and (lab != np.argmin(np.where(np.isfinite(cost), cost, 9), 1)).any()
    keep = face != 7
    try:
        select_views_sparse(n * n, face[keep], label[keep], cost[face, label][keep], adj, 0.8)
    except ValueError as e:
        assert "at least one" in str(e)
    else:
        raise AssertionError("a face without a label was accepted")


def _segment_meets_box(p, q, lo, hi) -> bool:
    """Slab test: does the segment p -> q meet the box [lo, hi]?"""
    d = q - p
    t0, t1 = 0.0, 1.0
    for k in range(3):
        if abs(d[k]) < 1e-15:
            if p[k] < lo[k] or p[k] > hi[k]:
                return False
            continue
        a, b = sorted(((lo[k] - p[k]) / d[k], (hi[k] - p[k]) / d[k]))
        t0, t1 = max(t0, a), min(t1, b)
        if t0 > t1:
            return False
    return True


def test_occluders_dropped_before_the_scene_meet_no_visibility_ray():
    """voxels_between keeps every voxel a ray from near a face of the region to a camera meets (the dropped
    ones cannot change a visibility test) and drops most of a small region's box of occluders."""
    from tasks.repair.region_texture import RAY_START_M, voxels_between

    rng = np.random.default_rng(11)
    lo, hi = np.array([0.0, 0.0, 1.0]), np.array([1.5, 0.2, 3.0])
    cams = [camera_at(np.array([x, 8.0, 1.6]), [0.7, 0.1, 2.0], f"c{i}") for i, x in enumerate((-6.0, 0.0, 5.0))]
    voxel = 0.2
    vox = rng.uniform([-10, -5, 0], [10, 15, 6], (4000, 3))
    keep = voxels_between(vox, lo, hi, cams, voxel)
    starts = rng.uniform(lo, hi, (300, 3))
    starts += rng.normal(size=starts.shape) * (RAY_START_M / np.sqrt(3) / 3)  # off the face, within the reach
    met = np.zeros(len(vox), bool)
    for i, v in enumerate(vox):
        for c in cams:
            if any(_segment_meets_box(s, c.centre, v - voxel / 2, v + voxel / 2) for s in starts[::7]):
                met[i] = True
                break
    assert met.sum() > 20 and not (met & ~keep).any()
    assert keep.mean() < 0.25  # a small region's rays sweep a thin fan, not the whole box
