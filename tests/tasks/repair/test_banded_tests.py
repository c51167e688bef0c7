"""Two speed-ups of the repair's inner loops give exactly what the plain versions gave: voxel thinning on one
packed int64 key per voxel (instead of unique rows), and the point-in-polygon test of a chart's boundary
on v-bands of sorted points (instead of every point against every edge)."""

from __future__ import annotations

import numpy as np

from tasks.repair.fuse import thin_points
from tasks.repair.mesh import _inside_polygon


def _thin_reference(xyz, voxel_m):
    """One point per voxel, the nearest to its voxel's centroid (the lowest index on a tie), in plain Python."""
    voxels: dict[tuple, list[int]] = {}
    for i, c in enumerate(np.floor(np.asarray(xyz, np.float64) / voxel_m).astype(np.int64).tolist()):
        voxels.setdefault(tuple(c), []).append(i)
    keep = []
    for members in voxels.values():
        centre = xyz[members].sum(axis=0) / len(members)
        d = np.linalg.norm(xyz[members] - centre, axis=1)
        keep.append(members[int(np.argmin(d))])
    return np.sort(np.array(keep, np.int64))


def _inside_reference(poly, pts, eps):
    inside, clear = np.zeros(len(pts), bool), np.ones(len(pts), bool)
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        yi = (a[1] > pts[:, 1]) != (b[1] > pts[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = a[0] + (pts[:, 1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
        inside ^= yi & (pts[:, 0] < xc)
        d = b - a
        t = np.clip(((pts - a) @ d) / max(float(d @ d), 1e-30), 0.0, 1.0)
        clear &= np.linalg.norm(pts - (a + t[:, None] * d), axis=1) > eps
    return inside & clear


def test_thinning_keeps_the_same_points():
    rng = np.random.default_rng(0)
    for scale, offset in ((3.0, 0.0), (0.2, 5e5), (40.0, -2e3)):
        xyz = rng.normal(0, scale, (20_000, 3)) + offset
        got = thin_points(xyz, 0.05)
        np.testing.assert_array_equal(got, _thin_reference(xyz, 0.05))
        assert 0 < len(got) <= len(xyz)
    far = np.array([[0.0, 0, 0], [2e5, 0, 0], [0.01, 0, 0]])  # 4e6 voxels apart: the unique-rows path
    np.testing.assert_array_equal(thin_points(far, 0.05), _thin_reference(far, 0.05))


def test_point_in_polygon_on_bands_equals_every_edge_against_every_point():
    rng = np.random.default_rng(1)
    for trial in range(10):
        th = np.sort(rng.uniform(0, 2 * np.pi, 200))
        r = 1 + 0.5 * rng.uniform(size=200)
        poly = np.c_[r * np.cos(th), r * np.sin(th)]
        poly[:5, 1] = poly[5, 1]  # horizontal edges
        pts = rng.uniform(-1.6, 1.6, (5_000, 2))
        pts[:100] = poly[rng.integers(0, 200, 100)]  # on the vertices
        pts[100:140, 1] = poly[:40, 1]  # at vertex heights
        pts[140:150] = (poly[:10] + poly[1:11]) / 2  # on edges
        want = _inside_reference(poly, pts, 1e-6)
        assert 0 < want.sum() < len(pts)
        np.testing.assert_array_equal(_inside_polygon(poly, pts, 1e-6), want)
