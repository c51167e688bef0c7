"""A clean mesh with a real production's structure is graded good: node borders, hairline cracks, texture
seams, slivers and duplicated faces are not defects (``synth.cracked_production``).

The tiny synth campus's truth mesh (subdivided to production-like 0.6 m edges) is cut into 12 m nodes with
3 mm cracks, 4 m texture charts, 2 % slivers and 0.2 % duplicated faces: after welding coincident vertices
about 6-7 % of its edges stay open, as in a real ContextCapture production (7.6 %). The campus's MLS was
ray-cast from that same truth, so the scan agrees with the mesh everywhere: the right answer is "keep the
mesh". The shipped grading path (the default trees, the evidence rule) must call at most 3 % of its graded
patches bad. The trees that shipped before the cues were restricted to what the scan says graded open edges
as holes.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import trimesh

from flows.campus import InlineExecutor, run_campus
from storage.formats.meshes import read_mesh
from storage.formats.ply import write_ply
from synth.cracked_production import crack_production, open_edge_share
from tasks.config import CampusConfig

GOAL_BAD_SHARE = 0.03


@pytest.fixture(scope="module")
def cracked_campus(tiny_campus, tmp_path_factory):
    """(config, work dir, open edge share) of the tiny campus with its truth, cracked, as the input mesh."""
    import json

    root = tmp_path_factory.mktemp("cracked")
    origin = np.asarray(json.loads((tiny_campus / "truth" / "registration.json").read_text())["frame_origin"])
    m = read_mesh(tiny_campus / "truth" / "truth_mesh.ply")
    v, f = trimesh.remesh.subdivide_to_size(np.asarray(m.vertices) - origin, np.asarray(m.faces), max_edge=0.6)
    v, f = crack_production(np.random.default_rng(5), v, f)
    write_ply(root / "production.ply", v + origin, f)
    cfg = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {
        "work_dir": str(root / "work"), "runner": "inline",
        "inputs": {"mesh": [str(root / "production.ply")], "points": [str(tiny_campus / "mls")],
                   "crs": "EPSG:32650", "labels": None, "images": None, "cameras": None},
        "repair.enabled": False, "report.enabled": False})
    run_campus(cfg, executor=InlineExecutor())
    return cfg, root / "work", open_edge_share(f, v)


def test_the_mesh_is_a_non_watertight_production(cracked_campus):
    _, _, share = cracked_campus
    assert 0.04 < share < 0.12


def test_a_clean_non_watertight_production_is_graded_good(cracked_campus):
    _, work, _ = cracked_campus
    grades = np.concatenate([pd.read_parquet(p, columns=["grade"])["grade"].to_numpy()
                             for p in sorted((work / "tiles").glob("*/grades.parquet"))])
    graded = int((grades >= 0).sum())
    bad = int((grades == 1).sum())
    assert graded > 300
    assert bad / graded <= GOAL_BAD_SHARE, f"{bad} of {graded} graded patches bad ({bad / graded:.1%})"
