"""The viewer: served on localhost, rendered by headless Debian chromium, checked from pixel statistics."""

from __future__ import annotations

import json
import os
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
    if os.environ.get("MS3D_UPDATE_DOCS"):  # refresh docs/viewer.png on request, never as a side effect
        shutil.copyfile(shot, DOCS_PNG)


def _points_overlay_like_export(work: Path) -> int:
    """Write output/points/ as the export does, from the leaf contents' vertices (the tiny export has no
    patch stores): every point "no face" (magenta). Returns the number of points."""
    from tasks.export.content import box_from_bounds
    from tasks.export.georef import gltf_to_enu
    from tasks.export.gltf import glb_positions
    from tasks.export.points import build_points_glb, points_tileset_json

    out = work / "output"
    transform = json.loads((out / "tileset.json").read_text())["root"]["transform"]
    (out / "points").mkdir(exist_ok=True)
    boxes, n = {}, 0
    for leaf in sorted((out / "content" / "tiles").glob("*.glb")):
        pos = glb_positions(leaf.read_bytes())[::7]
        enu = gltf_to_enu(pos)
        boxes[leaf.stem] = box_from_bounds(enu.min(axis=0), enu.max(axis=0))
        (out / "points" / leaf.name).write_bytes(build_points_glb(pos, np.full(len(pos), 2, np.int8)))
        n += len(pos)
    (out / "points" / "tileset.json").write_text(json.dumps(points_tileset_json(boxes, transform)))
    return n


def test_headless_viewer_overlays_the_points_tileset(tiny_export, tmp_path):
    _tools_or_fail()
    from PIL import Image

    from tasks.export.check import check_tileset

    work = tmp_path / "work"
    shutil.copytree(tiny_export[0], work)
    n = _points_overlay_like_export(work)
    assert check_tileset(work / "output" / "points") == []
    shots = {}
    server = start_viewer(work)
    try:
        for show in ("0", "1"):
            shot = tmp_path / f"points{show}.png"
            run = subprocess.run(["node", str(VIEWER_DIR / "screenshot.mjs"), server.url + f"&showPoints={show}&pointSize=3",
                                  str(shot), "1024", "700", "120000"], check=False, capture_output=True, text=True,
                                 timeout=180)  # fmt: skip
            assert run.returncode == 0, run.stderr[-2000:]
            result = json.loads(run.stdout)
            assert result["ready"] and not result["state"]["errors"], result
            shots[show] = (result["state"]["points"], np.asarray(Image.open(shot).convert("RGB")).astype(np.int32)[150:])
    finally:
        server.stop()
    off, on = shots["0"][0], shots["1"][0]
    assert on["available"] and on["shown"] and on["models"] == 6 and on["count"] == n
    assert off["available"] and not off["shown"] and off["models"] == 0  # not loaded while hidden
    magenta = [((rgb[..., 0] > 150) & (rgb[..., 2] > 120) & (rgb[..., 1] < 90)).mean() for _, rgb in shots.values()]
    assert magenta[0] < 0.001 and magenta[1] > 0.01, magenta


def _relocate(work: Path, lat: float, lon: float, height: float) -> None:
    """Move the exported tileset (and its points overlay, if any) to (lat, lon, height): its root transform
    becomes the ENU -> ECEF frame there (the content stays in its ENU frame)."""
    from storage.formats.srs import geodetic_to_ecef
    from tasks.export.georef import enu_rotation

    m = np.eye(4)
    m[:3, :3] = enu_rotation(lon, lat).T  # columns: east, north, up in ECEF
    m[:3, 3] = geodetic_to_ecef(lat, lon, height)
    path = work / "output" / "tileset.json"
    doc = json.loads(path.read_text())
    doc["root"]["transform"] = [float(v) for v in m.T.reshape(-1)]
    path.write_text(json.dumps(doc))


@pytest.mark.parametrize("place", ["demo", "amsterdam"])
def test_viewer_frames_the_model_upright_in_its_local_frame(tiny_export, tmp_path, place):
    """At the demo's latitude and at Amsterdam's (52.37 N), the camera's up is the local vertical, the view
    looks down at about 45 degrees, the image's up is the local up, and the model fills the frame."""
    _tools_or_fail()
    from PIL import Image

    work = tmp_path / "work"
    shutil.copytree(tiny_export[0], work)
    if place == "amsterdam":
        _relocate(work, 52.3676, 4.9041, 43.0)
    shot = tmp_path / f"{place}.png"
    server = start_viewer(work)
    try:
        run = subprocess.run(["node", str(VIEWER_DIR / "screenshot.mjs"), server.url + "&measure=420,560,620,560",
                              str(shot), "1024", "700", "120000"], check=False, capture_output=True, text=True,
                             timeout=180)  # fmt: skip
    finally:
        server.stop()
    assert run.returncode == 0, run.stderr[-2000:]
    result = json.loads(run.stdout)
    assert result["ready"] and not result["state"]["errors"], result
    v = result["view"]
    if place == "amsterdam":
        assert v["lat"] == pytest.approx(52.3676, abs=0.05) and v["lon"] == pytest.approx(4.9041, abs=0.05), v
    assert v["upDot"] > 0.9999, v  # the camera's up is the local vertical
    assert v["imageUpDot"] > 0.6, v  # the image's up points up (cos 45 deg ~ 0.71), not sideways
    assert 40.0 <= v["pitchDeg"] <= 50.0, v  # looking down at the model, above its horizon
    m = result["measure"]  # two points picked on the model, 200 px apart on screen
    a, b = (np.array(p) for p in m["points"])
    assert m["distance"] == pytest.approx(np.linalg.norm(b - a), abs=1e-6) and m["distance"] > 0.5, m
    assert m["horizontal"] ** 2 + m["height"] ** 2 == pytest.approx(m["distance"] ** 2, rel=1e-6), m
    rgb = np.asarray(Image.open(shot).convert("RGB")).astype(np.int32)[150:]
    drawn = np.abs(rgb - BACKGROUND).sum(axis=2) > 30
    assert drawn.mean() > 0.1, f"only {drawn.mean():.1%} of the pixels show the model"
    if os.environ.get("MS3D_UPDATE_DOCS"):
        shutil.copyfile(shot, DOCS_PNG.with_name(f"viewer-{place}.png"))


def test_before_after_split_shows_the_input_beside_the_merged_model(tiny_work, tmp_path):
    """export.before writes output/before/ (the input mesh as a tileset); the viewer loads it with
    ?compare=1, clips it left of the split and the merged model right of it, and counts the input's faces
    apart from the merged model's (which stay those of the view without the split)."""
    _tools_or_fail()
    from PIL import Image

    from tasks.config import ExportConfig
    from tasks.export import run_export
    from tasks.export.check import check_tileset

    work = tmp_path / "work"
    shutil.copytree(tiny_work[1].root, work, ignore=shutil.ignore_patterns("staging", "output", "export", "prefect"))
    summary = run_export(work, ExportConfig(before=True))
    assert summary["before"]["tiles"] == summary["tiles"] and check_tileset(work / "output" / "before") == []
    input_faces = sum(json.loads(p.read_text())["n_faces"] for p in (work / "export" / "before" / "tiles").glob("*/merged.json"))
    shots = {}
    server = start_viewer(work)
    try:
        for compare in ("0", "1"):
            shot = tmp_path / f"compare{compare}.png"
            run = subprocess.run(["node", str(VIEWER_DIR / "screenshot.mjs"), server.url + f"&errorTarget=0&compare={compare}",
                                  str(shot), "1024", "700", "120000"], check=False, capture_output=True, text=True,
                                 timeout=180)  # fmt: skip
            assert run.returncode == 0, run.stderr[-2000:]
            result = json.loads(run.stdout)
            assert result["ready"] and not result["state"]["errors"], result
            shots[compare] = (result["state"], np.asarray(Image.open(shot).convert("RGB")).astype(np.int32)[150:])
    finally:
        server.stop()
    off, on = shots["0"][0], shots["1"][0]
    assert off["before"]["available"] and not off["before"]["shown"] and off["before"]["models"] == 0
    # every input leaf loaded (errorTarget 0); coarser levels loaded on the way count too
    assert on["before"]["shown"] and on["before"]["faces"] >= input_faces > 0
    assert on["faces"] == off["faces"]  # the merged model's counts are its own
    # the input has no rebuilt (blue) faces: with the split, the left half loses blue, the right keeps it
    blue = lambda rgb: ((rgb[..., 2] > rgb[..., 0] + 60) & (rgb[..., 2] > rgb[..., 1] + 30))
    w = shots["1"][1].shape[1] // 2
    assert blue(shots["1"][1][:, :w]).sum() < blue(shots["0"][1][:, :w]).sum()
    assert blue(shots["1"][1][:, w:]).sum() > 0
