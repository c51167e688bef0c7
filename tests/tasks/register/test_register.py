"""tasks.register.align: SAC-IA + Scale-ICP recover a known similarity on a synthetic street.

The scene is built here: box buildings (walls + flat roofs) on both sides of a road along x, and a
ground plane. The mesh (target) is a dense, noisy photogrammetric stand-in: every surface is a
jittered 10 cm vertex grid, two triangles per cell, with 2 cm vertex noise. The MLS stand-in
(source) samples only the road-facing facades, the first 4 m of the side walls (seen through the
gaps) and the ground near the road, at 8 cm with 5 mm noise, and is then moved by the inverse of a
known similarity, so that ``target ~= TRUTH(source)``. Coarse (LoD2-like) meshes are tested in
``test_register_surface.py``.
"""

from __future__ import annotations

import numpy as np
import pytest

from storage.errors import InputError
from synth.generate import similarity
from synth.handmade import jittered_parallelogram as _rect
from tasks.config import RegistrationConfig
from tasks.register.align import (
    RegistrationResult,
    apply_similarity,
    check_coregistered,
    compare_transforms,
    decompose_similarity,
    fine_register,
    mesh_registration_target,
    register_clouds,
    subsample_for_registration,
    surface_planes,
)

# (x0, x1, facade y, depth, height), metres; north buildings extend to +y, south ones to -y
NORTH = [(-32.0, -14.0, 8.0, 12.0, 12.0), (-9.0, 8.0, 9.5, 10.0, 16.0), (13.0, 30.0, 8.0, 12.0, 9.0)]
SOUTH = [(-28.0, -6.0, -9.0, 12.0, 10.0), (0.0, 26.0, -8.0, 14.0, 18.0)]


def _grid_mesh(origin, u, v, spacing, rng):
    """The parallelogram origin + a u + b v as a vertex grid ~``spacing`` apart (interior vertices
    jittered), two triangles per cell: (vertices (k, 3) float64, faces (f, 3) int64)."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    nu, nv = max(int(np.linalg.norm(u) / spacing), 1), max(int(np.linalg.norm(v) / spacing), 1)
    a, b = np.meshgrid(np.arange(nu + 1) / nu, np.arange(nv + 1) / nv, indexing="ij")
    a[1:-1, :] += rng.uniform(-0.3, 0.3, a[1:-1, :].shape) / nu
    b[:, 1:-1] += rng.uniform(-0.3, 0.3, b[:, 1:-1].shape) / nv
    vertices = np.asarray(origin, float) + a.ravel()[:, None] * u + b.ravel()[:, None] * v
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    c = (i * (nv + 1) + j).ravel()
    faces = np.concatenate([np.stack([c, c + nv + 1, c + nv + 2], 1), np.stack([c, c + nv + 2, c + 1], 1)])
    return vertices, faces


def _street(seed=0):
    """(source (n, 3), mesh vertices (m, 3), mesh faces (f, 3)): float64 metres, the target (mesh) frame."""
    rng = np.random.default_rng(seed)
    parts = [_grid_mesh((-40, -25, 0), (80, 0, 0), (0, 50, 0), 0.10, rng)]
    src = [_rect((-35, -7.5, 0), (70, 0, 0), (0, 15, 0), 0.08, rng)]
    for buildings, sign in ((NORTH, 1.0), (SOUTH, -1.0)):
        for x0, x1, yf, depth, h in buildings:
            yb = yf + sign * depth
            faces = [
                ((x0, yf, 0), (x1 - x0, 0, 0), (0, 0, h)),  # front (road side)
                ((x0, yb, 0), (x1 - x0, 0, 0), (0, 0, h)),  # back
                ((x0, yf, 0), (0, yb - yf, 0), (0, 0, h)),  # sides
                ((x1, yf, 0), (0, yb - yf, 0), (0, 0, h)),
                ((x0, yf, h), (x1 - x0, 0, 0), (0, yb - yf, 0)),  # roof
            ]
            parts += [_grid_mesh(*f, 0.10, rng) for f in faces]
            src.append(_rect(*faces[0], 0.08, rng))
            src += [_rect((x, yf, 0), (0, sign * 4.0, 0), (0, 0, h), 0.08, rng) for x in (x0, x1)]
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    vertices = np.concatenate([p[0] for p in parts])
    faces = np.concatenate([p[1] + o for p, o in zip(parts, offsets)])
    src = np.concatenate(src)
    return src + rng.normal(0, 0.005, src.shape), vertices + rng.normal(0, 0.02, vertices.shape), faces


def _similarity(yaw_deg, roll_deg, pitch_deg, t, scale):
    return similarity(scale, yaw_deg, pitch_deg, roll_deg, t)  # R = Rz(yaw) Ry(pitch) Rx(roll)


TRUTH = _similarity(3.0, 0.5, -0.3, (2.5, -1.7, 0.8), 1.003)


@pytest.fixture(scope="module")
def street():
    src, vertices, faces = _street()
    return apply_similarity(np.linalg.inv(TRUTH), src), src, (vertices, faces)


def test_recovers_known_similarity(street):
    moved, _, mesh = street
    res = register_clouds(moved, *mesh, RegistrationConfig())
    err = compare_transforms(res.matrix, TRUTH, at=moved.mean(axis=0))
    print(f"\nregistration {res.method}: {err}, {res.seconds:.1f} s, {res.details['seconds']}")
    assert isinstance(res, RegistrationResult) and res.matrix.shape == (4, 4)
    assert err["rotation_error_deg"] < 0.05
    assert err["translation_error_m"] < 0.02
    assert abs(err["scale_error_pct"]) < 0.05
    assert res.scale == pytest.approx(1.003, abs=5e-4)
    assert res.fitness > 0.9 and res.inlier_rmse_m < 0.05  # 2 cm vertex noise dominates the residual
    assert res.n_source <= RegistrationConfig().max_points
    assert res.method.startswith("sac-ia+")


def test_aligned_pair_returns_identity(street):
    _, src, (vertices, faces) = street
    src, west = src[src[:, 0] < 0.0], (vertices[faces, 0] < 10.0).all(axis=1)  # the west half: faster
    res = register_clouds(src, vertices, faces[west], RegistrationConfig(max_points=100_000))
    err = compare_transforms(res.matrix, np.eye(4), at=src.mean(axis=0))
    assert err["rotation_error_deg"] < 0.05
    assert err["translation_error_m"] < 0.02
    assert abs(err["scale_error_pct"]) < 0.05


def test_check_coregistered_flags_an_offset(street):
    _, src, mesh = street
    check = check_coregistered(src, *mesh)
    assert check.ok and check.median_m < 0.03 and check.overlap_fraction == 1.0
    # 1 m along the street, across it, up, and diagonally: each slides most points along some surfaces
    for offset in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0), np.ones(3) / np.sqrt(3.0)):
        check = check_coregistered(src + offset, *mesh)
        assert not check.ok and check.median_m > 0.5, (offset, check)


def test_disabled_registration_warns_and_returns_identity(street):
    _, src, mesh = street
    with pytest.warns(UserWarning, match="co-registered"):
        res = register_clouds(src + (0.0, 1.0, 0.0), *mesh, RegistrationConfig(enabled=False))
    assert np.array_equal(res.matrix, np.eye(4)) and res.method.startswith("identity")


def test_degenerate_inputs_raise_input_error():
    rng = np.random.default_rng(0)
    good = rng.uniform(0, 10, (1000, 3))
    v, f = _grid_mesh((0, 0, 0), (10, 0, 0), (0, 10, 0), 1.0, rng)
    cfg = RegistrationConfig()
    with pytest.raises(InputError, match="at least 100"):
        register_clouds(good[:50], v, f, cfg)
    with pytest.raises(InputError, match="NaN"):
        register_clouds(np.full((500, 3), np.nan), v, f, cfg)
    with pytest.raises(InputError, match="mesh has no faces with finite vertices"):
        register_clouds(good, np.full_like(v, np.nan), f, cfg)
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        register_clouds(good[:, :2], v, f, cfg)
    with pytest.raises(InputError, match="mesh faces must be an"):
        register_clouds(good, v, f[:, :2], cfg)
    with pytest.raises(InputError, match="do not overlap"):
        register_clouds(good, v + (5000.0, 0.0, 0.0), f, cfg)
    with pytest.raises(InputError, match="do not overlap"):  # x/y overlap, but 200 m apart in height
        register_clouds(good, v + (0.0, 0.0, 200.0), f, cfg)


def test_similarity_algebra_on_three_points():
    m = _similarity(90.0, 0.0, 0.0, (1.0, 2.0, 3.0), 2.0)
    pts = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    np.testing.assert_allclose(apply_similarity(m, pts), [[1, 4, 3], [-1, 2, 3], [1, 2, 5]], atol=1e-12)
    s, r, t = decompose_similarity(m)
    assert s == pytest.approx(2.0) and np.allclose(r @ r.T, np.eye(3)) and np.allclose(t, (1, 2, 3))
    off = _similarity(91.0, 0.0, 0.0, (1.0, 2.0, 3.0), 2.0 * 1.001)
    err = compare_transforms(off, m, at=(10.0, 0.0, 0.0))
    assert err["rotation_error_deg"] == pytest.approx(1.0)
    assert err["scale_error_pct"] == pytest.approx(0.1)
    # (10, 0, 0) lands at 20.02 m from t at 91 degrees instead of 20 m at 90 degrees
    expected = np.hypot(20.02 * np.sin(np.radians(1.0)), 20.02 * np.cos(np.radians(1.0)) - 20.0)
    assert err["translation_error_m"] == pytest.approx(expected)
    with pytest.raises(ValueError):
        decompose_similarity(np.diag([1.0, 1.0, -1.0, 1.0]))


def test_subsample_caps_and_is_deterministic():
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0, 10, (200_000, 3))
    a = subsample_for_registration(xyz, 5_000, 0.5, np.random.default_rng(1))
    b = subsample_for_registration(xyz, 5_000, 0.5, np.random.default_rng(1))
    assert a.shape == (5_000, 3) and np.array_equal(a, b)
    assert a.min() >= 0 and a.max() <= 10
    thinned = subsample_for_registration(xyz, 10**6, 0.5, np.random.default_rng(1))
    assert 20**3 <= len(thinned) <= 21**3  # one centroid per occupied 0.5 m voxel of the 10 m cube


def test_surface_planes_denoise_a_plane():
    rng = np.random.default_rng(2)
    xyz = _rect((0, 0, 0), (10, 0, 0), (0, 10, 0), 0.1, rng) + rng.normal(0, 0.02, (10_000, 3))
    centres, normals = surface_planes(xyz)
    assert centres.shape == normals.shape and len(centres) < 0.5 * len(xyz)  # ~0.2 m apart
    assert np.std(centres[:, 2]) < 0.3 * np.std(xyz[:, 2])  # 24 neighbours average the noise
    assert np.median(np.abs(normals[:, 2])) > 0.99


def test_fine_stage_ignores_a_proud_facade(street):
    """A mesh facade 15 cm proud of the truth (a 'melted' MVS facade) must not drag the fit."""
    moved, _, mesh = street
    tgt, _ = mesh_registration_target(*mesh)
    proud = (np.abs(tgt[:, 1] - 9.5) < 0.2) & (tgt[:, 0] > -9) & (tgt[:, 0] < 8)
    tgt[proud, 1] -= 0.15
    cfg = RegistrationConfig()
    src = subsample_for_registration(moved, 100_000, cfg.fine_voxel_m, np.random.default_rng(0))
    init = _similarity(0.5, 0.1, -0.1, (0.2, -0.2, 0.1), 1.0 / 1.003) @ TRUTH  # a typical coarse result
    centres, normals = surface_planes(tgt[np.abs(tgt[:, 1]) < 15])
    matrix, fitness, rmse, _ = fine_register(src, centres, normals, init, cfg, np.random.default_rng(0))
    err = compare_transforms(matrix, TRUTH, at=moved.mean(axis=0))
    assert fitness > 0.8 and rmse < 0.05
    assert err["rotation_error_deg"] < 0.01
    assert err["translation_error_m"] < 0.005
    assert abs(err["scale_error_pct"]) < 0.01
