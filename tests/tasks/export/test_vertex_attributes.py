"""The export's per-vertex attributes against references built here: area-weighted normals (up where
undefined), the sRGB table on every 8-bit value, the feature split's two paths."""

import numpy as np

from tasks.export.gltf import EXPORT_NORMALS, srgb_to_linear_u8
from tasks.export.vertex_split import split_by_feature
from tasks.geometry.triangles import vertex_normals


def _numpy_vertex_normals(positions, faces):
    p = positions.astype(np.float64)
    fn = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    acc = np.stack([np.bincount(faces.reshape(-1), np.repeat(fn[:, d], 3), minlength=len(p)) for d in range(3)], 1)
    norm = np.linalg.norm(acc, axis=1)
    out = np.tile([0.0, 1.0, 0.0], (len(p), 1))
    out[norm > 1e-20] = acc[norm > 1e-20] / norm[norm > 1e-20, None]
    return out.astype(np.float32)


def test_vertex_normals_equal_the_bincount_sums_and_point_up_where_undefined():
    rng = np.random.default_rng(0)
    pos = rng.normal(size=(2000, 3)).astype(np.float32)
    faces = rng.integers(0, 1990, size=(5000, 3)).astype(np.int32)  # the last 10 vertices are unused
    faces[:3] = [[0, 0, 1], [4, 5, 4], [7, 7, 7]]  # degenerate faces add nothing
    got = vertex_normals(pos, faces, **EXPORT_NORMALS).astype(np.float32)
    np.testing.assert_array_equal(got, _numpy_vertex_normals(pos, faces))
    np.testing.assert_array_equal(got[-10:], np.tile(np.float32([0, 1, 0]), (10, 1)))
    flat = vertex_normals(np.float32([[0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]), **EXPORT_NORMALS)
    np.testing.assert_allclose(flat, np.tile([0, 0, 1], (3, 1)))  # counter-clockwise in xy: +z


def test_srgb_table_equals_the_formula_on_every_value():
    c = np.arange(256) / 255.0
    ref = np.clip(np.round(np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4) * 255), 0, 255)
    rgb = np.stack([np.arange(256), np.arange(256)[::-1], np.full(256, 128)], 1).astype(np.uint8)
    out = srgb_to_linear_u8(rgb)
    np.testing.assert_array_equal(out[:, 0], ref.astype(np.uint8))
    np.testing.assert_array_equal(out[:, 1], ref[::-1].astype(np.uint8))
    assert (out[:, 3] == 255).all() and out[128, 2] == 55  # sRGB 128 is 21.6 % linear


def test_split_by_feature_single_feature_path_equals_the_general_one():
    rng = np.random.default_rng(1)
    faces = np.arange(3000).reshape(1000, 3)  # no vertex shared: the single-feature path
    faces = faces[rng.permutation(1000)] % 2995  # ... except a few, within one feature
    feature = np.zeros(1000, np.int64)
    f1, s1, d1 = split_by_feature(faces, feature)
    key = faces.reshape(-1)
    uniq, inv = np.unique(key, return_inverse=True)
    np.testing.assert_array_equal(f1, inv.reshape(-1, 3))
    np.testing.assert_array_equal(s1, uniq)
    assert (d1 == 0).all()
    feature[faces[:, 0] < 5] = 1  # now shared vertices carry two features: split, the general path
    f2, s2, d2 = split_by_feature(faces, feature)
    assert len(s2) > len(s1)
    assert (d2[f2] == feature[:, None]).all() and (s2[f2] == faces).all()
