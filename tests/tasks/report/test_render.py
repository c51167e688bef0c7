"""The region renders' rasteriser: at every pixel centre the nearest covering face wins (checked against a
pixel-by-pixel reference on random triangles), and a render of a few hundred thousand faces is a PNG."""

from __future__ import annotations

import numpy as np

from tasks.report.figures import rasterise, render_png, view_basis


def _reference(xy, depth, rgb, lo, hi, px):
    span = hi - lo
    step = span.max() / px
    w, h = int(np.ceil(span[0] / step)), int(np.ceil(span[1] / step))
    img = np.zeros((h, w, 4))
    for r in range(h):
        for c in range(w):
            q = lo + (np.array([c, r]) + 0.5) * step
            best = np.inf
            for t in range(len(xy)):
                a, b, d = xy[t]
                e = [(b - a)[0] * (q - a)[1] - (b - a)[1] * (q - a)[0],
                     (d - b)[0] * (q - b)[1] - (d - b)[1] * (q - b)[0],
                     (a - d)[0] * (q - d)[1] - (a - d)[1] * (q - d)[0]]
                if (min(e) >= 0 or max(e) <= 0) and depth[t] < best:
                    best, img[r, c, :3], img[r, c, 3] = depth[t], rgb[t], 1.0
    return img


def test_the_nearest_covering_face_wins_at_every_pixel():
    rng = np.random.default_rng(3)
    centres = rng.uniform(0, 10, (40, 1, 2))
    xy = centres + rng.normal(0, 1.5, (40, 3, 2))
    depth, rgb = rng.uniform(0, 5, 40), rng.uniform(0, 1, (40, 3))
    lo, hi = np.array([0.0, 0.0]), np.array([10.0, 7.0])
    got = rasterise(xy, depth, rgb, lo, hi, px=24)
    want = _reference(xy, depth, rgb, lo, hi, 24)
    assert got.shape == want.shape == (17, 24, 4)
    assert 0.2 < want[..., 3].mean() < 1.0  # some pixels covered, some not
    np.testing.assert_array_equal(got, want)
    xy[5, 1, 0], depth[6] = np.nan, np.nan  # a broken face paints nothing and costs nothing
    want = _reference(np.delete(xy, [5, 6], 0), np.delete(depth, [5, 6]), np.delete(rgb, [5, 6], 0), lo, hi, 24)
    np.testing.assert_array_equal(rasterise(xy, depth, rgb, lo, hi, px=24), want)


def test_a_render_of_many_faces_is_a_png():
    rng = np.random.default_rng(0)
    base = rng.uniform(0, 20, (300_000, 1, 3)) * [1, 0, 1]
    tri = base + rng.normal(0, 0.05, (300_000, 3, 3))
    col = np.tile([0.8, 0.8, 0.8], (len(tri), 1))
    png = render_png([("before", tri, col), ("after", tri[:1000], col[:1000])],
                     view_basis(np.array([[0.0, -1.0, 0.0]])), "a wall")
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
