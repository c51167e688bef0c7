"""3D Tiles output formats side by side: geometry none / Draco / meshopt, textures JPEG / KTX2, on one merged work dir.

Each variant exports a copy of the work dir's merged tiles (``run_export`` in this process, one after the
other) and prints, per level (leaves, each parent level, the overview): files and bytes on disk (what a
viewer downloads to show that level) and gzipped (with HTTP compression), texture bytes, the GPU memory the level's textures take once decoded
(JPEG / PNG: RGBA8 with mipmaps, 4 x 4/3 bytes per pixel; KTX2: the transcoded block format, ETC1S -> BC1 /
ETC1 at 0.5 byte per pixel, UASTC -> BC7 / ASTC 4x4 at 1 byte per pixel, with its mipmaps), the export's wall
time, and the viewer's time to show the whole campus (headless chromium, software WebGL: page load until
every tile is loaded and settled, ``errorTarget=0``) with the per-face grades it decoded. ``none+jpeg+vc`` is
``none+jpeg`` with vertex-coloured parents (``export.lod_texture_px: 0``, the export before textured parents);
``--shots DIR`` saves each variant's parents as the viewer shows them from its own framing (a large
screen-space error target, so the coarse levels stay on screen), for the same distance side by side.

    .venv/bin/python benchmarks/tile_formats_bench.py --merged WORKDIR [--max-texture-px 1024] [--variants ...]
    .venv/bin/python benchmarks/tile_formats_bench.py --mesh root.3mxb --tile-size 8 --variants none+jpeg none+jpeg+vc
        [--tiling implicit] [--archive]

``--tiling implicit`` exports every variant as implicit tiling (levels from the implicit paths, the subtrees
as a row of their own); ``--archive`` also packs each into ``output/tileset.3tz`` and prints its size.

Always exits 0: it reports. KTX2 encoding is slow on CPU (ktx2-encoder's Basis encoder in WebAssembly), so
the default caps atlases at 1024 px for every variant (the same cap for JPEG, for a fair comparison).
"""

from __future__ import annotations

import argparse
import gzip
import json
import shutil
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._common import machine
from benchmarks.export_bench import copy_merged

# name: (compression, texture, parents' largest atlas side in px: None the default (textured), 0 vertex-coloured)
VARIANTS = {"none+jpeg": ("none", "jpeg", None), "draco+jpeg": ("draco", "jpeg", None),
            "meshopt+jpeg": ("meshopt", "jpeg", None), "meshopt+ktx2": ("meshopt", "ktx2", None),
            "none+jpeg+vc": ("none", "jpeg", 0)}


def _glb_json(data: bytes) -> dict:
    n = struct.unpack("<I", data[12:16])[0]
    return json.loads(data[20:20 + n])


def _image_gpu_bytes(doc: dict, data: bytes) -> tuple[int, int]:
    """(encoded texture bytes, estimated GPU bytes) of a glb's images."""
    n = struct.unpack("<I", data[12:16])[0]
    bin_start = 20 + n + 8
    enc = gpu = 0
    for im in doc.get("images", []):
        bv = doc["bufferViews"][im["bufferView"]]
        raw = data[bin_start + bv.get("byteOffset", 0): bin_start + bv.get("byteOffset", 0) + bv["byteLength"]]
        enc += len(raw)
        if im.get("mimeType") == "image/ktx2":
            w, h = struct.unpack("<II", raw[20:28])
            dfd_model = raw[struct.unpack("<I", raw[48:52])[0] + 12] if len(raw) > 64 else 0
            per_px = 0.5 if dfd_model == 163 else 1.0  # KTX2 DFD colour model 163: ETC1S; else UASTC (166)
        else:
            from io import BytesIO

            from PIL import Image

            w, h = Image.open(BytesIO(raw)).size
            per_px = 4.0
        gpu += int(w * h * per_px * 4 / 3)
    return enc, gpu


def level_of(path: Path, out: Path, levels: int = 0) -> str:
    """leaves, lod{h} or overview; ``levels``: an implicit tileset's availableLevels (its paths name levels
    from the root: content/{level}/{x}/{y}.glb)."""
    rel = path.relative_to(out).as_posix()
    if rel == "overview.glb":
        return "overview"
    part = rel.split("/")[1]
    if part.isdigit():
        h = levels - 1 - int(part)
        return "leaves" if h == 0 else f"lod{h}"
    return "leaves" if rel.startswith("content/tiles/") else part  # content/lod{h}/...


def measure(out: Path) -> dict:
    doc = json.loads((out / "tileset.json").read_text())
    n_levels = doc["root"].get("implicitTiling", {}).get("availableLevels", 0)
    levels: dict[str, dict] = {}
    for p in sorted(out.rglob("*.subtree")):  # implicit tiling's availability
        lv = levels.setdefault("subtrees", {"files": 0, "bytes": 0, "gzip_bytes": 0, "texture_bytes": 0,
                                            "gpu_texture_bytes": 0})
        lv["files"] += 1
        lv["bytes"] += p.stat().st_size
        lv["gzip_bytes"] += len(gzip.compress(p.read_bytes(), 6))
    for p in sorted(out.rglob("*.glb")):
        if "points" in p.relative_to(out).parts:
            continue
        data = p.read_bytes()
        enc, gpu = _image_gpu_bytes(_glb_json(data), data)
        lv = levels.setdefault(level_of(p, out, n_levels), {"files": 0, "bytes": 0, "gzip_bytes": 0, "texture_bytes": 0,
                                                  "gpu_texture_bytes": 0})
        lv["files"] += 1
        lv["bytes"] += len(data)
        lv["gzip_bytes"] += len(gzip.compress(data, 6))  # the download with HTTP gzip
        lv["texture_bytes"] += enc
        lv["gpu_texture_bytes"] += gpu
    return levels


def viewer_time(work: Path, query: str = "&errorTarget=0", shot: Path | None = None) -> tuple[float, dict]:
    """Seconds until the viewer (headless chromium) has loaded and settled the tileset with ``query`` added
    to its URL, and the per-grade faces it decoded; the screenshot goes to ``shot`` when given."""
    from flows.view import VIEWER_DIR, start_viewer

    node = shutil.which("node")
    if node is None:
        return float("nan"), {}
    server = start_viewer(work)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            run = subprocess.run([node, str(VIEWER_DIR / "screenshot.mjs"), server.url + query,
                                  str(shot or Path(tmp) / "shot.png"), "1024", "700", "600000"], capture_output=True,
                                 text=True, check=False, timeout=900)
            wall = time.perf_counter() - t0
    finally:
        server.stop()
    try:
        res = json.loads(run.stdout)
    except json.JSONDecodeError:
        return float("nan"), {}
    return (wall if res.get("ready") else float("nan")), res.get("state", {}).get("faces", {})


def _merged_from_mesh(mesh_path: Path, out: Path, tile_size_m: float) -> Path:
    """A work dir of merged tiles cut from a mesh file (fake provenance), at UTM 31N (500 km E, 5,400 km N)."""
    from dataclasses import replace

    import numpy as np

    from storage.formats.meshes import read_mesh
    from storage.frame import CampusFrame
    from synth.tile_meshes import fake_merged_workdir

    origin = (500_000.0, 5_400_000.0, 100.0)
    mesh = read_mesh(str(mesh_path))
    mesh = replace(mesh, vertices=mesh.vertices + np.array(origin))
    frame = CampusFrame(origin=origin, crs="EPSG:32631", vertical_datum="ellipsoidal (WGS 84), arbitrary")
    shutil.rmtree(out, ignore_errors=True)
    return fake_merged_workdir(mesh, frame, out, tile_size_m=tile_size_m).root


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--merged", type=Path, help="a processed work dir (its tiles/*/merged.*)")
    src.add_argument("--mesh", type=Path, help="a mesh file (OBJ, PLY, 3MX/3MXB, glb, ...) cut into --tile-size tiles "
                     "with fake provenance (synth.tile_meshes), placed at an arbitrary UTM origin: a real "
                     "production's textures without running the pipeline")
    ap.add_argument("--tile-size", type=float, default=8.0)
    ap.add_argument("--max-texture-px", type=int, default=1024)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--work", type=Path, help="where the copies go (default: a temporary folder)")
    ap.add_argument("--tiling", choices=["explicit", "implicit"], default="explicit")
    ap.add_argument("--archive", action="store_true", help="also pack output/tileset.3tz and print its size")
    ap.add_argument("--shots", type=Path, help="save each variant's view of its parents here ({variant}.png: the "
                    "photo textures, the viewer's own framing, a screen-space error target of --shot-error px)")
    ap.add_argument("--shot-error", type=float, default=2000.0)
    a = ap.parse_args(argv)
    from functools import partial

    from tasks.config import ExportConfig
    from tasks.export import run_export

    # every variant in the layout asked for
    ExportConfig = partial(ExportConfig, tiling=a.tiling, archive="3tz" if a.archive else "none")

    tmp = tempfile.TemporaryDirectory(prefix="ms3d-formats-")
    root = a.work or Path(tmp.name)
    if a.mesh:
        a.merged = _merged_from_mesh(a.mesh, root / "_merged", a.tile_size)
    print(f"machine: {machine()}; merged tiles of {a.merged}; atlases capped at {a.max_texture_px} px")
    rows = {}
    for name in a.variants:
        compression, texture, parents_px = VARIANTS[name]
        work = root / name
        if work.exists():
            shutil.rmtree(work)
        copy_merged(a.merged, work, 0.0)  # texture paths made absolute: the copies read the source's textures
        t0 = time.perf_counter()
        run_export(work, ExportConfig(compression=compression, texture=texture, max_texture_px=a.max_texture_px,
                                      **({} if parents_px is None else {"lod_texture_px": parents_px})))
        export_s = time.perf_counter() - t0
        view_s, faces = viewer_time(work)
        if a.shots:
            a.shots.mkdir(parents=True, exist_ok=True)
            viewer_time(work, f"&errorTarget={a.shot_error:g}&mode=texture", a.shots / f"{name}.png")
        rows[name] = {"export_s": export_s, "viewer_s": view_s, "faces": faces, "levels": measure(work / "output")}
    print(f"\n{'variant':<14} {'level':<9} {'files':>5} {'MB on disk':>10} {'MB gzip':>8} {'MB textures':>11} "
          f"{'MB GPU tex':>10}")
    for name, r in rows.items():
        for lv, m in sorted(r["levels"].items()):
            print(f"{name:<14} {lv:<9} {m['files']:>5} {m['bytes'] / 1e6:>10.2f} {m['gzip_bytes'] / 1e6:>8.2f} "
                  f"{m['texture_bytes'] / 1e6:>11.2f} {m['gpu_texture_bytes'] / 1e6:>10.2f}")
    print(f"\n{'variant':<14} {'export s':>8} {'viewer s':>8} {'MB total':>8} {'MB .3tz':>8}  faces the viewer "
          f"decoded ({a.tiling} tiling)")
    for name, r in rows.items():
        total = sum(m["bytes"] for m in r["levels"].values()) / 1e6
        arc = root / name / "output" / "tileset.3tz"
        packed = f"{arc.stat().st_size / 1e6:>8.2f}" if arc.exists() else f"{'-':>8}"
        print(f"{name:<14} {r['export_s']:>8.1f} {r['viewer_s']:>8.1f} {total:>8.2f} {packed}  {r['faces']}")
    if not a.work:
        tmp.cleanup()


if __name__ == "__main__":
    main()
