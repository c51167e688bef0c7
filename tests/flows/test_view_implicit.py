"""The viewer on an implicit tileset served from a 3D Tiles archive: headless chromium decodes the subtrees
(3d-tiles-renderer's ImplicitTilingPlugin) and the archive's entries, and shows the same leaves, with the same
per-face grades, as the explicit export of the same tiles."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import pytest

from flows.view import VIEWER_DIR, start_viewer
from tasks.config import ExportConfig
from tasks.export import run_export

CHROMIUM = Path("/usr/bin/chromium")


def _render(source: Path, shot: Path) -> dict:
    """The viewer's summary (screenshot.mjs) of ``source`` (a work dir or a .3tz) loaded down to the leaves."""
    server = start_viewer(source)
    try:
        run = subprocess.run(["node", str(VIEWER_DIR / "screenshot.mjs"), server.url + "&errorTarget=0", str(shot),
                              "800", "600", "150000"], check=False, capture_output=True, text=True, timeout=200)
    finally:
        server.stop()
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(run.stdout)


def test_headless_viewer_shows_the_implicit_archive_like_the_explicit_export(tiny_merged, tiny_export, tmp_path):
    if shutil.which("node") is None or not CHROMIUM.exists():
        pytest.fail("node and Debian chromium are needed (apt-get install -y nodejs chromium)")
    for pkg in ("playwright-core", "three", "3d-tiles-renderer"):
        if not (VIEWER_DIR / "node_modules" / pkg).is_dir():
            pytest.fail(f"viewer/node_modules/{pkg} missing (npm ci --prefix viewer)")
    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work)
    run_export(work, ExportConfig(tiling="implicit", subtree_levels=2, archive="3tz"))  # a subtree per leaf
    archive = tmp_path / "campus.3tz"
    shutil.move(work / "output" / "tileset.3tz", archive)  # served alone: nothing read from the folder
    shutil.rmtree(work / "output")
    implicit = _render(archive, tmp_path / "implicit.png")
    explicit = _render(tiny_export[0], tmp_path / "explicit.png")
    for result in (implicit, explicit):
        assert result["ready"] and not result["state"]["errors"], result
        probes = ("/output/points/tileset.json", "/output/before/tileset.json")  # optional overlays: 404 here
        bad = [m for m in result["console"] if m.startswith("pageerror") or m.startswith("http") and not m.endswith(probes)]
        assert not bad, bad
    assert implicit["state"]["faces"] == explicit["state"]["faces"] and implicit["state"]["faces"]["good"] > 0
