"""synth.coarse: the LoD2-like block model of the synth buildings and its departure labels."""

from __future__ import annotations

import numpy as np

from synth.coarse import CoarseParams, block_model, departure_defects
from synth.generate import _tile_scene
from synth.presets import get_preset
from synth.scene import FaceClass


def test_block_model_is_coarse_and_departures_are_labelled():
    scene = _tile_scene(7, get_preset("tiny"), 0, 0, 1)  # one building with balconies
    model = block_model(scene)
    on_b = model.face_building >= 0
    tri = model.vertices[model.faces[on_b]]
    assert on_b.sum() < 100 and np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2).max(axis=1).min() > 2.0
    assert not np.isin(model.face_class, [FaceClass.GLASS, FaceClass.BALCONY]).any()
    # terrain is the truth's, untouched
    assert (model.face_building < 0).sum() == (scene.truth.face_building < 0).sum()
    defects = departure_defects(scene, model, CoarseParams(depart_m=0.2))
    kinds = {d["type"] for d in defects}
    assert kinds == {"recess", "balcony"}
    for d in defects:
        s = np.asarray(d["samples"])
        assert len(s) and d["faces"] == [] and np.allclose(d["bbox"], [*s.min(0), *s.max(0)])
    # a looser tolerance labels fewer samples, and one beyond every departure labels none
    n = lambda p: sum(len(d["samples"]) for d in departure_defects(scene, model, CoarseParams(depart_m=p)))
    assert n(0.2) > n(0.5) > 0 and n(5.0) == 0
