"""Things standing on the ground are not triangulated into it (tasks.repair.standing)."""

import numpy as np

from tasks.repair.chart import zone_charts
from tasks.repair.mesh import rebuild_charts
from tasks.repair.standing import standing_points


def _plane(n: int = 8, size: float = 4.0, vertical: bool = False):
    """A size x size grid of 2 n² faces: the ground (z = 0, wound up) or a wall (y = 0, wound towards -y)."""
    g = np.linspace(0, size, n + 1)
    a, b = (x.ravel() for x in np.meshgrid(g, g, indexing="ij"))
    v = np.c_[a, b, np.zeros_like(a)] if not vertical else np.c_[a, np.zeros_like(a), b]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    f = []
    for i in range(n):
        for j in range(n):
            f += [[idx[i, j], idx[i + 1, j], idx[i + 1, j + 1]], [idx[i, j], idx[i + 1, j + 1], idx[i, j + 1]]]
    return v, np.array(f)


def _ground_and_person(step: float = 0.05):
    """Ground samples (normals up) over 4 x 4 m and a person's legs at (2, 2): a 0.15 m cylinder from the
    ground to 0.6 m, normals sideways (what the fusion's reach lets into a ground region)."""
    g = np.arange(step / 2, 4, step)
    a, b = (x.ravel() for x in np.meshgrid(g, g))
    ground = np.c_[a, b, np.zeros_like(a)]
    t, h = np.meshgrid(np.linspace(0, 2 * np.pi, 24, endpoint=False), np.arange(0.0, 0.6, 0.04))
    side = np.c_[np.cos(t.ravel()), np.sin(t.ravel()), np.zeros(t.size)]
    r = 0.15 + np.random.default_rng(0).uniform(-0.02, 0.02, t.size)  # a scan's spread: no two points stacked
    legs = np.c_[2 + r[:, None] * side[:, :2], h.ravel()]
    pts = np.concatenate([ground, legs])
    nrm = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(ground), 1)), side])
    return pts, nrm, len(ground)


def _rebuild(v, f, pts, nrm, stand_off_m):
    topo = zone_charts(v, f, np.zeros((0, 3), int), np.zeros(len(v), bool), max_hole_loop_m=1.0)
    assert len(topo.charts) == 1
    return rebuild_charts(topo.charts, np.arange(len(v)), pts, np.ones(len(pts), np.int8), np.full(len(pts), -1),
                          max_map_distance_m=1.2, border_margin_m=0.02, max_edge_m=0.6, pts_normal=nrm,
                          stand_off_m=stand_off_m)


def test_a_persons_legs_pull_a_spike_from_the_ground_unless_they_are_left_out():
    v, f = _plane()
    if np.cross(v[f[0, 1]] - v[f[0, 0]], v[f[0, 2]] - v[f[0, 0]])[2] < 0:
        f = f[:, ::-1]
    pts, nrm, n_ground = _ground_and_person()
    spiked = _rebuild(v, f, pts, nrm, stand_off_m=0.0)
    assert spiked.xyz[:, 2].max() > 0.3  # the failure the rule exists for
    clean = _rebuild(v, f, pts, nrm, stand_off_m=0.05)
    assert clean.xyz[:, 2].max() <= 0.05
    assert 0 < clean.stats["standing"] <= len(pts) - n_ground


def test_a_walls_relief_and_a_raised_slab_stay():
    v, f = _plane(vertical=True)  # a wall: its relief's sides face sideways, across the wall's normal
    pts, nrm, _ = _ground_and_person()
    wall_pts = pts[:, [0, 2, 1]]
    wall_pts[:, 1] *= -1
    m = _rebuild(v, f, wall_pts, nrm[:, [0, 2, 1]] * [1, -1, 1], stand_off_m=0.05)
    assert m.stats["standing"] == 0
    foot = np.zeros((3, 3))
    up = np.tile([0.0, 0.0, 1.0], (3, 1))
    slab = np.array([[0, 0, 0.2], [0, 0, -0.3], [0, 0, 0.04]], float)  # a raised slab, a recess, the ground's noise
    sideways = np.tile([0.0, 1.0, 0.0], (3, 1))
    assert not standing_points(slab, up, foot, up, min_offset_m=0.05).any()
    assert standing_points(slab, sideways, foot, up, min_offset_m=0.05).tolist() == [True, False, False]
    assert not standing_points(slab, sideways, foot, up, min_offset_m=0.0).any()  # off: every point stays
