"""The registration guard through the campus flow (inline, up to partition) on the synth 'tiny' campus:
a re-registration that fails after an input change keeps the recorded transform and says so; co-registered
inputs stay where they are."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from flows.campus import InlineExecutor, run_campus
from flows.summary import format_summary
from storage.errors import InputError
from storage.formats.points import read_points, write_points
from tasks.config import CampusConfig

EARLY = {"classify.enabled": False, "repair.enabled": False, "report.enabled": False, "runner": "inline"}


def _run(campus, work, **over):
    return run_campus(CampusConfig.from_yaml(campus / "campus.yaml", {**EARLY, "work_dir": str(work), **over}),
                      executor=InlineExecutor())


def test_a_failed_reregistration_keeps_the_recorded_transform(tiny_campus, tmp_path, monkeypatch):
    campus, work = tmp_path / "campus", tmp_path / "work"
    shutil.copytree(tiny_campus, campus)
    strips = sorted((campus / "mls").glob("*.laz"))
    assert len(strips) == 2
    first = _run(campus, work)["registration"]
    assert first["verdict"]["chosen"] == "estimate" and first["distance_after_m"] < 0.05
    recorded = json.loads((work / "registration.json").read_text())["matrix"]

    strips[1].unlink()  # the remaining strip re-registers; make that fit fail as a degenerate scene does

    def lost(*a, **k):
        raise InputError(None, "ICP lost the overlap: 0 source points within 0.15 m")

    monkeypatch.setattr("tasks.register.align.register_to_samples", lost)
    s = _run(campus, work)
    reg = s["registration"]
    assert reg["verdict"]["chosen"] == "recorded" and not s["tiles_failed"]
    assert json.loads((work / "registration.json").read_text())["matrix"] == recorded
    lines = [x for x in format_summary(s).splitlines() if x.startswith("warning: registration")]
    assert len(lines) == 1 and "kept the recorded transform: the re-registration failed" in lines[0]
    assert "ICP lost the overlap" in lines[0]


@pytest.fixture
def coregistered(tiny_campus, tmp_path):
    """The tiny campus with its true registration applied to the MLS strips (so the inputs coincide)."""
    campus = tmp_path / "coreg"
    shutil.copytree(tiny_campus, campus)
    truth = json.loads((campus / "truth" / "registration.json").read_text())
    m, o = np.asarray(truth["matrix_mls_to_mesh"]), np.asarray(truth["frame_origin"])
    for p in sorted((campus / "mls").glob("*.laz")):
        pc = read_points(p)
        write_points(p, dataclasses.replace(pc, xyz=(pc.xyz - o) @ m[:3, :3].T + m[:3, 3] + o), crs=truth["crs"])
    return campus


def test_auto_leaves_coregistered_inputs_where_they_are(coregistered, tmp_path):
    reg = _run(coregistered, tmp_path / "work")["registration"]
    assert reg["displacement_max_m"] < 0.02, reg
    assert reg["distance_before_m"] < 0.05 and reg["verdict"]["chosen"] == "identity"
    rec = json.loads((tmp_path / "work" / "registration.json").read_text())
    assert np.allclose(rec["matrix"], np.eye(4)) and rec["estimate"]["displacement_max_m"] < 0.1
