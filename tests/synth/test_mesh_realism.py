import numpy as np

from synth.mesh_realism import mesh_stats


def _grid(n=20, step=0.1, noise=0.0, vertical=True, seed=0):
    """A regular triangulated n x n grid (valence 6 inside), on a wall (x-z plane) or the ground."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    a, b = (i * step).ravel(), (j * step).ravel()
    off = np.random.default_rng(seed).normal(0, noise, a.shape)
    v = np.c_[a, off, b] if vertical else np.c_[a, b, off]
    idx = (i * n + j)
    q = np.c_[idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()]
    faces = np.r_[q[:, [0, 1, 2]], q[:, [0, 2, 3]]]
    return v, faces


def test_regular_grid_figures_are_exact():
    v, f = _grid()
    s = mesh_stats(v, f)
    assert s.valence6_fraction == 1.0
    assert np.isclose(s.edge_p10_m, 0.1) and np.isclose(s.edge_p90_m, 0.1 * np.sqrt(2))
    assert np.isclose(s.faces_per_m2, 200.0)  # two triangles per 0.1 m square
    assert np.isclose(s.facade_faces_per_m2, 200.0)
    assert s.facade_roughness_rms_m < 1e-9


def test_roughness_measures_noise_and_ground_is_not_facade():
    v, f = _grid(n=40, noise=0.008)
    assert 0.005 < mesh_stats(v, f).facade_roughness_rms_m < 0.009
    g, gf = _grid(vertical=False)
    assert np.isnan(mesh_stats(g, gf).facade_roughness_rms_m)
