"""Defects injected into an arbitrary mesh (synth.mesh_defects): a grid wall with window recesses."""

import numpy as np
import pytest

from synth.defects import DefectSpec
from synth.mesh_defects import MESH_DEFECT_TYPES, MeshDefectParams, inject_mesh_defects


def wall_mesh(w=20.0, h=10.0, step=0.1):
    """A wall in the x-z plane facing -y, 1.0 m above the ground, with 0.3 m deep window recesses."""
    xs, zs = np.arange(0, w + 1e-9, step), np.arange(1.0, 1.0 + h + 1e-9, step)
    X, Z = np.meshgrid(xs, zs)
    Y = np.zeros_like(X)
    window = (np.mod(X, 4.0) > 1.0) & (np.mod(X, 4.0) < 2.5) & (np.mod(Z, 3.0) > 1.0) & (np.mod(Z, 3.0) < 2.2)
    Y[window] = 0.3  # set back (behind the wall, away from the street at -y)
    v = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    nx = len(xs)
    i, j = np.meshgrid(np.arange(len(zs) - 1), np.arange(nx - 1), indexing="ij")
    a = (i * nx + j).ravel()
    f = np.concatenate([np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)])
    return v, f


def only(typ, rate=2.0, **kw):
    base = MeshDefectParams().specs
    return MeshDefectParams(specs={typ: DefectSpec(rate, *([base[typ].radius_m, base[typ].magnitude_m]))}, **kw)


@pytest.mark.parametrize("typ", MESH_DEFECT_TYPES)
def test_each_type_changes_the_mesh_where_its_samples_are(typ):
    v, f = wall_mesh()
    v_in = v.copy()
    out_v, out_f, defects = inject_mesh_defects(np.random.default_rng(3), v, f, only(typ))
    assert np.array_equal(v, v_in)  # the input is not modified
    if typ == "thin":  # the grid wall has nothing in front of it: no thin defect exists there
        assert defects == []
        return
    assert defects, typ
    assert out_f.min() >= 0 and out_f.max() < len(out_v)
    for d in defects:
        assert d["type"] == typ and d["building"] == -1
        s = np.asarray(d["samples"])
        assert len(s) and np.allclose(s.min(0), d["bbox"][:3]) and np.allclose(s.max(0), d["bbox"][3:])
        assert np.linalg.norm(s - d["centre"], axis=1).min() < d["radius_m"] + 0.2
    if typ == "hole":
        assert len(out_f) < len(f)
        # the samples lie on the truth (the wall or its recess), where the output has no face now
        s = np.concatenate([np.asarray(d["samples"]) for d in defects])
        assert np.isin(np.round(s[:, 1], 3), [0.0, 0.3]).mean() > 0.8
    else:
        assert len(out_f) == len(f)
        moved = np.linalg.norm(out_v - v, axis=1)
        assert moved.max() >= 0.03


def test_bridge_pulls_recesses_forward_and_leaves_flat_wall_alone():
    v, f = wall_mesh()
    out_v, _, defects = inject_mesh_defects(np.random.default_rng(5), v, f, only("bridge", rate=3.0))
    moved = np.linalg.norm(out_v - v, axis=1) >= 0.03
    assert moved.any()
    assert (v[moved, 1] > 0.05).mean() > 0.7  # what moved was mostly recess
    assert (out_v[moved, 1] < v[moved, 1]).all()  # forward, toward the street


def test_thin_removes_what_stands_in_front():
    v, f = wall_mesh()
    v = v.copy()
    col = (np.abs(np.mod(v[:, 0], 1.5) - 0.75) < 0.25) & (v[:, 2] > 2.0)
    v[col, 1] -= 0.5  # pilasters 0.5 m in front of the wall every 1.5 m
    out_v, out_f, defects = inject_mesh_defects(np.random.default_rng(0), v, f, only("thin", rate=5.0))
    assert defects
    s = np.concatenate([np.asarray(d["samples"]) for d in defects])
    assert (s[:, 1] < -0.3).mean() > 0.8 and len(out_f) < len(f)


def test_same_seed_same_defects_and_rate_scale():
    v, f = wall_mesh()
    a = inject_mesh_defects(np.random.default_rng(9), v, f)
    b = inject_mesh_defects(np.random.default_rng(9), v, f)
    assert [d["samples"] for d in a[2]] == [d["samples"] for d in b[2]] and np.array_equal(a[0], b[0])
    none = inject_mesh_defects(np.random.default_rng(9), v, f, MeshDefectParams(rate_scale=0.0))
    assert none[2] == [] and np.array_equal(none[0], v) and np.array_equal(none[1], f)


def test_discs_do_not_overlap():
    v, f = wall_mesh(40.0, 12.0, 0.2)
    _, _, defects = inject_mesh_defects(np.random.default_rng(1), v, f, MeshDefectParams(rate_scale=3.0))
    c = np.array([d["centre"] for d in defects])
    r = np.array([d["radius_m"] for d in defects])
    dist = np.linalg.norm(c[:, None] - c[None], axis=2) + np.eye(len(c)) * 1e9
    assert (dist >= r[:, None] + r[None] + 0.3 - 1e-9).all()
