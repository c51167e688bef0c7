"""Ground-floor through-passages (synth.passages): in the truth, absent from the block model, labelled."""

from dataclasses import replace

import numpy as np
import pytest

from synth.buildings import DEFAULT_FACADE, make_scene
from synth.coarse import CoarseParams, block_model, departure_defects
from synth.generate import _tile_scene
from synth.mvs import MvsParams, TruthCaster, make_mvs_mesh
from synth.passages import _inside, in_passage
from synth.presets import get_preset
from synth.scene import FaceClass


@pytest.fixture(scope="module")
def tiny():
    return _tile_scene(31, get_preset("tiny"), 0, 0, 1, passages=True)


def _axis_ray(p: dict, front: list[float]):
    """A ray at mid-height along the passage axis from 5 m in front of the front facade: origin, dir, length."""
    r = np.array(p["rect"])
    ax = int(np.argmax(np.abs(front)))
    o = np.array([*(0.5 * (r[:2] + r[2:])), 0.5 * p["height_m"]])
    o[ax] = (r[ax + 2] + 5.0) if front[ax] > 0 else (r[ax] - 5.0)
    d = np.zeros(3)
    d[ax] = -np.sign(front[ax])
    return o, d, p["depth_m"] + 10.0


def _check_passages(scene) -> int:
    m = scene.truth
    on_b = TruthCaster(m, m.face_building >= 0)
    c, n = m.triangles().mean(axis=1), m.face_normals()
    count = 0
    for b, info in zip(scene.buildings, scene.meta["buildings"]):
        p = info.get("passage")
        if p is None:
            continue
        count += 1
        o, d, length = _axis_ray(p, info["front_normal"])
        t, f = on_b.cast(o[None], d[None])
        assert not (t[0] < length and m.face_building[on_b.face_index[f[0]]] == b.id)  # straight through
        assert 3.0 <= p["width_m"] <= 5.0 and 2.2 <= p["height_m"] <= b.storey_height_m - 0.25
        tunnel = (in_passage(c, [info]) == b.id) & (m.face_building == b.id)
        assert set(np.unique(m.face_class[tunnel])) == {FaceClass.WALL, FaceClass.EAVE}
        q = c[tunnel] + 0.05 * n[tunnel]  # normals point into the passage (out of the solid)
        assert (in_passage(q, [info], tol=0.0) == b.id).all()
        floor = (in_passage(c, [info]) == b.id) & (m.face_building < 0)  # the ground runs through
        assert np.isclose(m.face_areas()[floor].sum(), p["width_m"] * p["depth_m"])
        # no window or door pane cut into the passage's walls or facades
        pane = (m.face_building == b.id) & np.isin(m.face_class, [FaceClass.GLASS, FaceClass.FRAME])
        assert not (in_passage(c[pane], [info], tol=0.5) >= 0).any()
    return count


def test_tiny_coarse_building_has_a_through_passage_the_block_model_lacks(tiny):
    assert _check_passages(tiny) == 1
    info = tiny.meta["buildings"][0]
    o, d, _ = _axis_ray(info["passage"], info["front_normal"])
    model = block_model(tiny)
    t, _ = TruthCaster(model, model.face_building >= 0).cast(o[None], d[None])
    assert abs(t[0] - 5.0) < 1e-3  # the block model is solid: hit at the front facade
    ground = model.triangles().mean(axis=1)[model.face_building < 0]
    assert not (in_passage(ground, tiny.meta["buildings"]) >= 0).any()  # nor does it keep the passage floor


def test_passages_in_l_shaped_and_many_buildings():
    fp = replace(DEFAULT_FACADE, passage_p=1.0)
    n_pass, n_l = 0, 0
    for seed in (0, 1, 2):
        s = make_scene(np.random.default_rng(seed), (0.0, 0.0, 200.0, 200.0), 6, storeys=(1, 8), facade=fp)
        n_pass += _check_passages(s)
        n_l += sum(d["cut"] is not None and "passage" in d for d in s.meta["buildings"])
    assert n_pass >= 12 and n_l >= 2


def test_passages_off_by_default():
    a = _tile_scene(7, get_preset("tiny"), 0, 0, 1)
    b = make_scene(np.random.default_rng(5), (0.0, 0.0, 120.0, 120.0), 3)
    c = make_scene(np.random.default_rng(5), (0.0, 0.0, 120.0, 120.0), 3, facade=replace(DEFAULT_FACADE, passage_p=0.0))
    assert not any("passage" in d for d in a.meta["buildings"] + b.meta["buildings"])
    assert np.array_equal(b.truth.faces, c.truth.faces) and np.array_equal(b.truth.vertices, c.truth.vertices)
    assert a.truth.n_faces == 1126 and _tile_scene(31, get_preset("tiny"), 0, 0, 1).truth.n_faces == 1122
    on = _tile_scene(7, get_preset("tiny"), 0, 0, 1, passages=True)
    assert "passage" in on.meta["buildings"][0] and on.truth.n_faces != a.truth.n_faces
    # only the passage's building changes: the other draws of the scene are the same
    assert np.array_equal(on.occluders.mesh.vertices, a.occluders.mesh.vertices)


def test_coarse_labels_a_passage_inside_the_block_solid(tiny):
    defects = departure_defects(tiny, block_model(tiny), CoarseParams())
    by = {d["type"]: np.asarray(d["samples"]) for d in defects}
    assert set(by) == {"recess", "balcony", "passage"} and len(by["passage"]) > 1000
    b, info = tiny.buildings[0], tiny.meta["buildings"][0]
    s = by["passage"]
    assert _inside(s[:, :2] - 0.01 * np.sign(s[:, :2] - b.footprint.mean(axis=0)), b.footprint).all()
    assert (in_passage(s, [info], tol=1e-3) == b.id).all() and s[:, 2].max() <= info["passage"]["height_m"] + 1e-3
    for t in ("recess", "balcony"):  # a passage sample is labelled once
        assert not (in_passage(by[t], [info], tol=-1e-3) >= 0).any()


def _open_and_nonmanifold_edges(mesh) -> tuple[int, int]:
    e = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), axis=1)
    _, c = np.unique(e, axis=0, return_counts=True)
    return int((c == 1).sum()), int((c > 2).sum())


def test_mvs_mesh_opens_the_passage_and_stays_welded(tiny):
    params = MvsParams(edge_facade_m=0.3, defects=None)
    mesh, _ = make_mvs_mesh(np.random.default_rng(0), tiny, params)
    info = tiny.meta["buildings"][0]
    o, d, length = _axis_ray(info["passage"], info["front_normal"])
    t, _ = TruthCaster(mesh, mesh.face_building >= 0).cast(o[None], d[None])
    assert not t[0] < length  # the lattice follows the passage through the building
    c = mesh.triangles().mean(axis=1)
    inside = in_passage(c, tiny.meta["buildings"], tol=0.01) >= 0
    assert {FaceClass.GROUND, FaceClass.WALL, FaceClass.EAVE} <= set(np.unique(mesh.face_class[inside]))
    # the passage's charts weld to the facades, the soffit and the floor: the only border is the extent's
    plain, _ = make_mvs_mesh(np.random.default_rng(0), _tile_scene(31, get_preset("tiny"), 0, 0, 1), params)
    assert _open_and_nonmanifold_edges(mesh) == _open_and_nonmanifold_edges(plain)


def test_coarse_synth_writes_the_passage_and_its_label(tmp_path):
    import json

    from synth.generate import generate

    out = generate("tiny", seed=31, out=tmp_path / "c", coarse_mesh=True)
    (b,) = json.loads((out / "truth" / "scene.json").read_text())["buildings"]
    defects = json.loads((out / "truth" / "defects.json").read_text())["defects"]
    assert "passage" in b and [d["building"] for d in defects if d["type"] == "passage"] == [b["id"]]
