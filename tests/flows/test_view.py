"""The viewer: served on localhost, rendered by headless Debian chromium, checked from pixel statistics."""

from __future__ import annotations

import json
import shutil
import subprocess
import urllib.request
from pathlib import Path

import numpy as np
import pytest

from flows.view import VIEWER_DIR, start_viewer

CHROMIUM = Path("/usr/bin/chromium")
DOCS_PNG = Path(__file__).resolve().parents[2] / "docs" / "viewer.png"
BACKGROUND = np.array([0xDD, 0xE4, 0xEA])  # the page's clear colour


def _tools_or_fail():
    """make test installs node, chromium and the viewer's npm packages: a missing one is a broken set-up,
    never a reason for the viewer tests to pass unseen."""
    if shutil.which("node") is None:
        pytest.fail("node is not installed (apt-get install -y nodejs npm)")
    if not CHROMIUM.exists():
        pytest.fail("Debian chromium is not installed (apt-get install -y chromium)")
    for pkg in ("playwright-core", "three", "3d-tiles-renderer"):
        if not (VIEWER_DIR / "node_modules" / pkg).is_dir():
            pytest.fail(f"viewer/node_modules/{pkg} missing (npm ci --prefix viewer)")


def test_server_serves_viewer_output_and_nothing_else(tiny_export):
    work, _ = tiny_export
    if not (VIEWER_DIR / "node_modules" / "three").is_dir():
        pytest.fail("viewer/node_modules missing (npm ci --prefix viewer)")
    server = start_viewer(work)
    try:
        base = server.url.split("/viewer/")[0]
        assert server.url.startswith("http://127.0.0.1:")
        tileset = json.loads(urllib.request.urlopen(f"{base}/output/tileset.json").read())
        assert tileset["asset"]["version"] == "1.1"
        assert b"importmap" in urllib.request.urlopen(f"{base}/").read()  # redirected to the page
        for bad in ("/output/../campus.json", "/etc/passwd", "/tiles/0_0/merged.json"):
            with pytest.raises(urllib.error.HTTPError):
                urllib.request.urlopen(base + bad)
    finally:
        server.stop()


def test_headless_screenshot_shows_the_buildings(tiny_export, tmp_path):
    _tools_or_fail()
    from PIL import Image

    work, _ = tiny_export
    shot = tmp_path / "viewer.png"
    server = start_viewer(work)
    try:
        run = subprocess.run(["node", str(VIEWER_DIR / "screenshot.mjs"), server.url + "&errorTarget=4", str(shot),
                              "1280", "800", "120000"], check=False, capture_output=True, text=True, timeout=180)  # fmt: skip
    finally:
        server.stop()
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(run.stdout)
    assert result["ready"], result
    assert not result["state"]["errors"], result["state"]
    faces = result["state"]["faces"]
    assert faces["good"] > 0 and faces["bad"] > 0 and faces["rebuilt"] > 0
    pick = result["pick"]  # the face under the centre of the screen, read from EXT_structural_metadata
    assert pick is not None and pick["grade"] in ("good", "bad", "unknown") and pick["source"] in ("mesh", "rebuilt")

    rgb = np.asarray(Image.open(shot).convert("RGB")).astype(np.int32)
    body = rgb[150:, :]  # below the info panel
    drawn = np.abs(body - BACKGROUND).sum(axis=2) > 30
    assert drawn.mean() > 0.2, f"only {drawn.mean():.1%} of the pixels differ from the background"
    assert body[drawn].std(axis=0).mean() > 10, "the model is drawn in one flat colour"
    r, g, b = (body[..., i] for i in range(3))
    green = drawn & (g > r + 30) & (g > b + 10)
    red = drawn & (r > g + 60) & (r > b + 60)
    blue = drawn & (b > r + 60) & (b > g + 30)
    assert green.mean() > 0.05 and (red.mean() + blue.mean()) > 0.002, (green.mean(), red.mean(), blue.mean())
    DOCS_PNG.parent.mkdir(exist_ok=True)
    shutil.copyfile(shot, DOCS_PNG)
