"""The tiny synth campus processed once per session (inline, classify off): (config, WorkDir)."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def tiny_work(tiny_campus, tmp_path_factory):
    from flows.campus import run_campus
    from storage.workdir import WorkDir
    from tasks.config import CampusConfig

    work = tmp_path_factory.mktemp("model-tiny") / "work"
    cfg = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {"work_dir": str(work), "runner": "inline",
                                                              "classify": {"enabled": False}})
    run_campus(cfg, progress=False)
    return cfg, WorkDir(work)
