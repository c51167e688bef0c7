"""quality_bench's evaluation: seen / unseen split and exact aggregation of per-class sums."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_spec = importlib.util.spec_from_file_location("quality_bench", Path(__file__).parents[2] / "benchmarks" / "quality_bench.py")
qb = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(qb)


def test_seen_scope_counts_only_the_seen_facade():
    # truth: two 2 x 2 m walls (class 2 = wall) side by side; the prediction covers the first one, 3 cm off
    v = np.array([[0, 0, 0], [2, 0, 0], [2, 0, 2], [0, 0, 2], [2, 0, 0], [4, 0, 0], [4, 0, 2], [2, 0, 2]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    cls = np.full(4, 2)
    seen = np.array([True, True, False, False])
    pred_v = v[:4] + [0, 0.03, 0]
    r = qb.evaluate(pred_v, f[:2], (v, f, cls), seen, spacing_m=0.05)
    assert r["seen"]["F5"] == pytest.approx(1.0) and r["seen"]["uncovered"] == pytest.approx(0.0)
    assert r["all"]["F5"] == pytest.approx(2 / 3, abs=0.01)  # precision 1, recall 1/2
    assert r["all"]["uncovered"] == pytest.approx(0.5, abs=0.01)
    assert r["seen"]["acc_m"] == pytest.approx(0.03, abs=1e-3)
    assert r["all"]["per_class"]["wall"]["F5"] == pytest.approx(r["all"]["F5"])


def test_assembly_keeps_region_local_ids_apart(tmp_path):
    """Two regions whose new vertices carry the same (region-local) negative ids must not be welded."""
    import json

    from storage.workdir.layout import read_campus
    from synth.corner_scene import write_campus_workdir
    from tasks.config import CampusConfig
    from tasks.regions import run_regions
    from tasks.repair import run_region

    wd, _ = write_campus_workdir(tmp_path / "w")
    cfg = CampusConfig.model_validate(read_campus(wd)["config"])
    cfg.repair.texture.enabled = False
    cfg.repair.fusion.mls_spacing_m = 0.08
    key = run_regions(cfg, wd)["regions"][0]
    run_region(key, cfg, wd)
    # a second region: a copy of the first under another key (same negative ids)
    import shutil

    plan = json.loads((wd.root / "regions" / "regions.json").read_text())
    twin = dict(plan["regions"][0], key="rtwin")
    plan["regions"].append(twin)
    (wd.root / "regions" / "regions.json").write_text(json.dumps(plan))
    shutil.copytree(wd.root / "regions" / key, wd.root / "regions" / "rtwin")
    twin_mesh = wd.root / "regions" / "rtwin" / "mesh.npz"
    with np.load(twin_mesh) as z:
        arr = {k: z[k] for k in z.files}
    arr["vertices"] = arr["vertices"] + np.float32([0.0, 0.0, 100.0])  # the twin floats 100 m up
    arr["vertex_id"] = np.where(arr["vertex_id"] >= 0, arr["vertex_id"] + (1 << 50), arr["vertex_id"])
    arr["replaced_row"] = arr["replaced_row"][:0]
    arr["replaced_tile"] = arr["replaced_tile"][:0]
    np.savez(twin_mesh, **arr)
    v, f, info = qb.assemble(wd.root)
    assert info["rebuilt_faces"] == 2 * len(arr["faces"])
    e = v[f]
    longest = np.linalg.norm(e - np.roll(e, -1, axis=1), axis=2).max()
    assert longest < 5.0  # no vertex of one region welded to the other (100 m away)


def test_the_campus_table_names_the_classes_a_variant_makes_worse():
    """Ground (class 0) and a wall (class 2): (e) drops half the ground and moves the wall closer, so the ground
    is named worse and the wall is not; a variant equal to (a) has none."""
    from _quality_eval import table

    v = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0], [0, 3, 0], [2, 3, 0], [2, 3, 2], [0, 3, 2]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    truth = (v, f, np.array([0, 0, 2, 2]))
    seen = np.ones(4, bool)
    a_v = v + [0, 0, 0.0]
    a_v[4:] += [0, 0.08, 0]  # (a): the wall 8 cm off
    e_v = a_v.copy()
    e_v[4:] -= [0, 0.08, 0]  # (e): the wall in place, half the ground gone
    res = {"a": qb.evaluate(a_v, f, truth, seen), "e": qb.evaluate(e_v, f[1:], truth, seen),
           "d": qb.evaluate(a_v, f, truth, seen)}
    assert res["e"]["campus"]["per_class"]["wall"]["F5"] > res["a"]["campus"]["per_class"]["wall"]["F5"]
    out = table(res)
    line = next(s for s in out.splitlines() if s.startswith("(e) classes worse"))
    assert "ground" in line and "wall" not in line
    assert "(d) classes worse than (a): none" in out
