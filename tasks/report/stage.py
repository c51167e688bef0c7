"""The run report: ``output/report.html``, one self-contained page per run (figures embedded as PNG data).

Sections, each from what the work dir holds (a section whose inputs are missing says so):

1. inputs and registration: ``campus.json`` (inputs, CRS, origin, grid), the recorded transform
   (``registration.json``) as rotation / scale / translation with its fitness and RMSE, and, for a synth
   campus, its error against the true transform;
2. the patch-count histograms with their normal fit (``report/patch_*_histogram.png``, outlier stage);
3. the class map: a top view of the patches coloured by score (classify's ``grades``), else by grade
   (the labels), written to ``report/class_map.png`` too;
4. per-stage units, times and peak memory from the manifest records (``manifest.d``);
5. quality against the truth where it exists (a synth campus): the merged model, and the input mesh
   when regions were rebuilt (cached in ``report/quality.json`` by the merged tiles' fingerprints);
6. before/after renders of the rebuilt regions (``report/regions/*.png``), when there are any;
7. the output: links to the tileset, overview and georeference, and the ``ms3d view`` command.

The stage :func:`run_report` reads only small tables, the merged tiles (one at a time, for quality and
region renders) and the patches of the regions it renders.
"""

from __future__ import annotations

import datetime
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from storage.atomic import file_sha256, write_bytes_atomic, write_json_atomic
from storage.errors import InputError
from storage.grid import PatchGrid
from storage.manifest import all_records
from storage.patch_store import PatchStore
from storage.tile_mesh import read_tile_mesh, tile_mesh_paths
from storage.workdir import WorkDir, campus_frame, read_campus
from tasks.report.figures import class_map_png
from tasks.report.html import Section, esc, render_page, table
from tasks.report.regions import regions_section

log = logging.getLogger("ms3d.report")
REPORT_VERSION = 1
QUALITY_TILE_M = 25.0  # quality is evaluated tile by tile (memory): distances capped at the buffer
QUALITY_BUFFER_M = 2.0


# ------------------------------------------------------------------------------ sections


def similarity_parts(matrix) -> dict:
    """A 4x4 similarity as scale, rotation angle (deg) and translation (m).

    >>> p = similarity_parts(np.diag([2.0, 2.0, 2.0, 1.0]))
    >>> round(p["scale"], 6), round(p["rotation_deg"], 6)
    (2.0, 0.0)
    """
    m = np.asarray(matrix, np.float64)
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    r = m[:3, :3] / s
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])  # 2 sin(angle) * unit axis
    angle = math.degrees(math.atan2(float(np.linalg.norm(axis)), float(np.trace(r) - 1)))  # exact near 0
    return {"scale": s, "rotation_deg": angle, "translation_m": m[:3, 3].tolist(),
            "translation_norm_m": float(np.linalg.norm(m[:3, 3]))}


def truth_dir_of(cfg) -> Path | None:
    """The synth campus folder whose ``truth/`` holds the truth mesh, if the inputs come from one."""
    candidates = []
    if cfg.inputs.labels:
        candidates.append(Path(cfg.inputs.labels).parent.parent)
    candidates += [Path(p).parent for p in cfg.inputs.mesh]
    for c in candidates:
        if (c / "truth").is_dir() and list((c / "truth").glob("truth_mesh*.ply")):
            return c
    return None


def inputs_section(campus: dict, wd: WorkDir, truth: Path | None) -> Section:
    frame = campus.get("frame", {})
    rows = [[Path(r["path"]).name, r["kind"], r.get("count"), r.get("crs") or "–",
             " × ".join(f"{h - lo:,.1f}" for lo, h in zip(r["lo"], r["hi"])) if r.get("lo") else "–",
             r.get("error") or "ok"] for r in campus.get("inputs", [])]  # fmt: skip
    body = table(["file", "kind", "points / faces", "CRS in file", "extent x × y × z (m)", "status"], rows)
    grid = campus.get("grid", {})
    body += table(["CRS", "origin (world m)", "vertical datum", "patch size (m)", "tile size (m)"], [[
        frame.get("crs"), ", ".join(f"{v:,.3f}" for v in frame.get("origin", [])), frame.get("vertical_datum"),
        " × ".join(str(v) for v in grid.get("size_m", [])), grid.get("tile_size_m")]])
    skipped = campus.get("skipped_files") or []
    if skipped:
        body += f"<p>skipped files: {esc(', '.join(str(s) for s in skipped[:20]))}</p>"
    reg = dict(campus.get("registration", {}))
    recorded = wd.root / "registration.json"
    if recorded.exists():
        reg = json.loads(recorded.read_text()) | {k: v for k, v in reg.items() if k in ("reused", "mode")}
    if "matrix" in reg:
        parts = similarity_parts(reg["matrix"])
        body += "<h3>Registration (MLS → mesh)</h3>" + table(
            ["method", "scale", "rotation (deg)", "translation (m)", "fitness", "inlier RMSE (m)", "coarse fitness",
             "points used", "seconds", "reused"],
            [[reg.get("method"), parts["scale"], parts["rotation_deg"],
              ", ".join(f"{v:.3f}" for v in parts["translation_m"]), reg.get("fitness"), reg.get("inlier_rmse_m"),
              reg.get("coarse_fitness"), reg.get("n_source"), reg.get("seconds"), reg.get("reused")]])  # fmt: skip
        if truth is not None and (truth / "truth" / "registration.json").exists():
            err = registration_error_m(reg["matrix"], truth, np.asarray(frame["origin"]), campus)
            body += (f"<p>Against the synth campus's true transform: the recovered one moves the campus's corners "
                     f"at most <b>{err * 1000:.1f} mm</b> away from where the truth puts them.</p>")
    return Section("Inputs and registration", body)


def registration_error_m(matrix, synth_dir: Path, origin: np.ndarray, campus: dict) -> float:
    """Largest distance between the recovered and the true MLS -> mesh transform over the corners of the
    inputs' bounding box (campus-local)."""
    reg = json.loads((synth_dir / "truth" / "registration.json").read_text())
    m_o = np.asarray(reg["matrix_mls_to_mesh"], np.float64)
    d = np.asarray(reg["frame_origin"], np.float64) - origin
    t1, t2 = np.eye(4), np.eye(4)
    t1[:3, 3], t2[:3, 3] = d, -d
    truth = t1 @ m_o @ t2
    lo = np.min([r["lo"] for r in campus.get("inputs", []) if r.get("lo")], axis=0) - origin
    hi = np.max([r["hi"] for r in campus.get("inputs", []) if r.get("hi")], axis=0) - origin
    corners = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    return float(np.linalg.norm(corners @ (np.asarray(matrix) - truth).T, axis=1).max())


def histogram_section(wd: WorkDir) -> Section:
    sec = Section("Patch counts and their fit")
    out = next((r.summary for r in all_records(wd) if r.stage == "outliers"), None)
    if out:
        rows = [[name, out[name]["mean_log10"], out[name]["std_log10"], out[name]["low"], out[name]["high"],
                 out[name]["flagged"]] for name in ("points", "faces") if name in out]  # fmt: skip
        sec.body += table(["per patch", "mean log10", "sd log10", "kept from", "kept to", "flagged"], rows)
    for p in sorted(wd.report_dir.glob("patch_*_histogram.png")):
        sec.figures[p.stem] = p.read_bytes()
    if not sec.figures:
        sec.body += "<p>No histograms (the outlier stage has not run).</p>"
    return sec


def class_map_section(wd: WorkDir, grid: PatchGrid, origin: np.ndarray) -> Section:
    sec = Section("Class map")
    ii, jj, vals, kinds = [], [], [], set()
    for t in wd.live_tiles():
        store = PatchStore(wd.tile_dir(t))
        p = store.patches()
        grades = store.side("grades")
        if grades is not None:
            v, kind = grades["score"].astype(np.float64), "score"
        else:
            labels = store.side("labels")
            v, kind = (labels["label"] if labels is not None else np.full(len(p["patch"]), -1)).astype(np.float64), "grade"
        kinds.add(kind)
        ii.append(p["i"])
        jj.append(p["j"])
        vals.append(v)
    if not ii:
        sec.body = "<p>No patch stores.</p>"
        return sec
    kind = "score" if kinds == {"score"} else "grade"
    value = np.concatenate(vals)
    if kind == "grade" and "score" in kinds:  # mixed (classify ran on some tiles only): grades for all
        value = np.where(np.isfinite(value) & (value >= 0), (value >= 0.5).astype(np.float64), -1.0)
    corner = (grid.anchor[:2] - origin[:2]).tolist()
    src = "classify scores" if kind == "score" else ("labels" if value.max() >= 0 else "no grades yet")
    png = class_map_png(np.concatenate(ii), np.concatenate(jj), value, kind, tuple(grid.size[:2]), tuple(corner),
                        f"{len(value):,} patches, top view ({src})")
    write_bytes_atomic(wd.report_dir / "class_map.png", png)
    sec.figures["class_map"] = png
    n_bad = int((value >= 0.5).sum()) if kind == "score" else int((value == 1).sum())
    sec.body = (f"<p>Each pixel is a column of patches (the worst over height) coloured by "
                f"{'score' if kind == 'score' else 'grade'} ({esc(src)}): {n_bad:,} of {len(value):,} patches bad.</p>")
    return sec


def stages_section(wd: WorkDir) -> Section:
    by_stage: dict[str, list] = {}
    for r in all_records(wd):
        by_stage.setdefault(r.stage, []).append(r)
    rows, errors = [], []
    for stage, recs in sorted(by_stage.items(), key=lambda kv: min(r.updated_at for r in kv[1])):
        secs = [r.seconds for r in recs]
        rss = [r.summary.get("peak_rss_mb") for r in recs if isinstance(r.summary.get("peak_rss_mb"), (int, float))]
        status = {s: sum(r.status == s for r in recs) for s in ("done", "empty", "failed")}
        rows.append([stage, len(recs), status["done"], status["empty"], status["failed"], float(sum(secs)),
                     float(max(secs)), f"{max(rss):,.0f}" if rss else "–"])
        errors += [f"{stage} {r.unit}: {r.error}" for r in recs if r.status == "failed"]
    body = table(["stage", "units", "done", "empty", "failed", "seconds (sum)", "seconds (slowest unit)",
                   "peak RSS MB"], rows)  # fmt: skip
    body += ("<p>Seconds are each unit's own work time (skipped units keep the time of the run that did them). "
             "Peak RSS is the largest over the stage's units of the worker process's resident memory while the unit "
             "ran (tasks.units resets the peak before each unit); – where the stage did not record it.</p>")
    if errors:
        body += "<h3>Failures</h3><ul>" + "".join(f"<li>{esc(e)}</li>" for e in errors[:50]) + "</ul>"
    return Section("Stages: time and memory", body)


def merged_tiles(wd: WorkDir) -> list[str]:
    return sorted(p.parent.name for p in (wd.root / "tiles").glob("*/merged.json"))


def _merged_fingerprint(wd: WorkDir, tiles: list[str]) -> str:
    import hashlib

    h = hashlib.sha256()
    for k in tiles:
        npz, meta = tile_mesh_paths(wd.root / "tiles" / k)
        h.update(k.encode() + meta.read_bytes() + str(npz.stat().st_size).encode() + str(npz.stat().st_mtime_ns).encode())
    return h.hexdigest()[:32]


def merged_surface(wd: WorkDir, tiles: list[str], shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The merged tiles as one mesh for quality: (vertices (n, 3) float64 = campus-local + ``shift``,
    faces (m, 3) int64). Each tile's vertices are welded by exact position (merge splits a vertex at
    seams only, every copy at one position), which cuts memory several times on seam-rich meshes."""
    from tasks.merge.weld import first_of_groups

    vs, fs, off = [], [], 0
    for k in tiles:
        tm = read_tile_mesh(wd.root / "tiles" / k)
        b = tm.vertices.view(np.uint32).astype(np.int64)
        group, first = first_of_groups((b[:, 0] << 32) | b[:, 1], b[:, 2])
        vs.append(tm.vertices[first].astype(np.float64) + shift)
        fs.append(group[tm.faces] + off)
        off += len(first)
    return np.concatenate(vs), np.concatenate(fs)


def quality_key(wd: WorkDir, truth: Path, tiles: list[str], any_rebuilt: bool, spacing_m: float = 0.05) -> dict:
    """What the cached quality figures depend on (merged tiles, truth, parameters)."""
    return {"version": REPORT_VERSION, "merged": _merged_fingerprint(wd, tiles), "spacing_m": spacing_m,
            "tile_m": QUALITY_TILE_M, "buffer_m": QUALITY_BUFFER_M,
            "truth": file_sha256(min((truth / "truth").glob("truth_mesh*.ply"))), "rebuilt": any_rebuilt}


def quality_share(wd: WorkDir, truth: Path, origin: np.ndarray, tiles: list[str], any_rebuilt: bool,
                  part: tuple[int, int], spacing_m: float = 0.05) -> dict:
    """The mergeable quality sums of one share of the quality tiles (``tasks.quality.metrics.evaluate_tiles``):
    {model name: QualityPartial or None}. Shares run as separate tasks; their sums add up exactly."""
    from storage.mesh_io import read_mesh
    from tasks.quality.metrics import evaluate_tiles, facade_mask
    from tasks.quality.truth import CLASS_NAMES, load_truth

    tv, tf, tc, t_origin = load_truth(truth)
    kw = {"tile_size_m": QUALITY_TILE_M, "buffer_m": QUALITY_BUFFER_M, "spacing_m": spacing_m,
          "true_face_mask": facade_mask(tc), "true_face_class": tc, "class_names": CLASS_NAMES, "part": part}
    v, f = merged_surface(wd, tiles, origin - t_origin)
    out = {"merged model": evaluate_tiles(v, f, tv - t_origin, tf, **kw)[0]}
    del v, f
    if any_rebuilt:
        mesh = read_mesh(truth / "mesh", offset=t_origin)
        out["input mesh"] = evaluate_tiles(mesh.vertices - t_origin, mesh.faces, tv - t_origin, tf, **kw)[0]
    return out


def write_quality(wd: WorkDir, key: dict, shares: list[dict]) -> dict:
    """Sum the shares into ``report/quality.json`` (the figures the report page shows)."""
    rows = {}
    for name in dict.fromkeys(n for s in shares for n in s):
        parts = [s[name] for s in shares if s.get(name) is not None]
        if parts:
            total = parts[0]
            for p in parts[1:]:
                total = total + p
            rows[name] = total.report().to_dict()
    cache = {"key": key, "rows": rows}
    write_json_atomic(wd.report_dir / "quality.json", cache)
    return cache


def ensure_quality(wd: WorkDir, truth: Path, origin: np.ndarray, tiles: list[str], any_rebuilt: bool,
                   spacing_m: float = 0.05) -> dict:
    """The quality figures of the merged model (and of the input mesh when regions were rebuilt) against the
    truth, computed (in this process) when ``report/quality.json`` does not hold them already."""
    cache_path = wd.report_dir / "quality.json"
    key = quality_key(wd, truth, tiles, any_rebuilt, spacing_m)
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    if cache.get("key") != key:
        cache = write_quality(wd, key, [quality_share(wd, truth, origin, tiles, any_rebuilt, (0, 1), spacing_m)])
    return cache


def quality_plan(cfg, wd: WorkDir) -> dict | None:
    """What a parallel quality run needs ({"key", "truth", "tiles", "rebuilt"}), or None when there is no
    truth, no merged tile, or the cache is already up to date."""
    from tasks.report.regions import any_rebuilt_region

    truth = truth_dir_of(cfg)
    tiles = merged_tiles(wd)
    if truth is None or not tiles:
        return None
    rebuilt = any_rebuilt_region(wd, tiles)
    key = quality_key(wd, truth, tiles, rebuilt)
    path = wd.report_dir / "quality.json"
    if path.exists() and json.loads(path.read_text()).get("key") == key:
        return None
    return {"key": key, "truth": str(truth), "tiles": tiles, "rebuilt": rebuilt}


def run_quality_share(cfg, wd: WorkDir, plan: dict, part: tuple[int, int]) -> dict:
    origin = campus_frame(read_campus(wd)).origin_array
    return quality_share(wd, Path(plan["truth"]), origin, plan["tiles"], plan["rebuilt"], part)


def quality_section(wd: WorkDir, truth: Path | None, origin: np.ndarray, tiles: list[str], any_rebuilt: bool,
                    spacing_m: float = 0.05) -> Section:
    sec = Section("Quality against the truth")
    if truth is None:
        sec.body = "<p>No truth for these inputs (quality is measured on synth campuses only).</p>"
        return sec
    if not tiles:
        sec.body = "<p>No merged tiles yet.</p>"
        return sec
    cache = ensure_quality(wd, truth, origin, tiles, any_rebuilt, spacing_m)
    rows = []
    for name, q in cache["rows"].items():
        rows.append([name, q["fscore"][0], q["fscore"][1], q["accuracy"]["mean_m"], q["completeness"]["mean_m"],
                      100 * q["uncovered_fraction"], q["evaluated_area_m2"]])  # fmt: skip
    sec.body = table(["model", "F@5 cm", "F@10 cm", "accuracy mean (m)", "completeness mean (m)",
                       "facade uncovered (%)", "facade area (m²)"], rows)
    per = cache["rows"]["merged model"].get("per_class", {})
    if per:
        sec.body += "<h3>Merged model per class</h3>" + table(
            ["class", "F@5 cm", "accuracy mean (m)", "completeness mean (m)", "area (m²)"],
            [[c, q["fscore"][0], q["accuracy"]["mean_m"], q["completeness"]["mean_m"], q["completeness"]["area_m2"]]
             for c, q in per.items()])  # fmt: skip
    sec.body += (f"<p>Surfaces sampled every {spacing_m * 100:g} cm, evaluated in {QUALITY_TILE_M:g} m tiles "
                 f"(distances capped at {QUALITY_BUFFER_M:g} m); uncovered: facade area of the truth with no "
                 "surface within 20 cm along its normal.</p>")
    if not any_rebuilt:
        sec.body += "<p>No region was rebuilt: the merged model is the input mesh, retained whole.</p>"
    return sec


def output_section(wd: WorkDir) -> Section:
    out = wd.root / "output"
    body = ""
    state = out / "tileset.fingerprints.json"
    if (out / "tileset.json").exists():
        nodes = json.loads(state.read_text()).get("nodes", {}) if state.exists() else {}
        leaves = [n for k, n in nodes.items() if k.startswith("L0_")]
        body += table(["tiles", "quadtree nodes", "leaf triangles", "bytes", "root geometric error (m)"], [[
            len(leaves), len(nodes), int(sum(n.get("faces", 0) for n in leaves)),
            int(sum(n.get("bytes", 0) for n in nodes.values())),
            float(json.loads((out / "tileset.json").read_text())["root"]["geometricError"])]])
        links = [(n, n) for n in ("tileset.json", "overview.glb", "georef.json") if (out / n).exists()]
        body += "<p>" + " · ".join(f'<a href="{esc(h)}">{esc(t)}</a>' for t, h in links) + "</p>"
    else:
        body += "<p>No tileset yet (the export stage has not run).</p>"
    body += (f"<p>Open the model in a browser: <code>ms3d view {esc(wd.root)}</code> "
             "(serves this folder's <code>output/</code> on localhost with the viewer page; colour by grade, "
             "source or region and click a face for its provenance).</p>")
    return Section("Output: 3D Tiles", body)


def _guarded(title: str, fn: Callable[[], Section]) -> Section:
    """A section, or a note saying why it could not be made (the report never fails for one section)."""
    try:
        return fn()
    except (InputError, OSError, ValueError, KeyError) as e:
        log.warning("report section %r: %s", title, e)
        return Section(title, f"<p class='note'>Could not make this section: {esc(e)}</p>")


def run_report(cfg, wd: WorkDir, truth_dir: str | Path | None = None, quality: bool = True) -> dict:
    """Write ``output/report.html`` (see the module docstring) and return a summary: path, figure names,
    sections, seconds. truth_dir: a synth campus folder (default: found from the inputs); quality=False
    skips the quality section (it samples the whole model: minutes on the demo, cached after)."""
    t0 = time.perf_counter()
    campus = read_campus(wd)
    origin = campus_frame(campus).origin_array
    grid = cfg.grid()
    truth = Path(truth_dir) if truth_dir is not None else truth_dir_of(cfg)
    tiles = merged_tiles(wd)
    regions: list[bool] = []

    def regions_fn() -> Section:
        sec, any_rebuilt = regions_section(wd, tiles, grid, origin)
        regions.append(any_rebuilt)
        return sec

    sections = [
        _guarded("Inputs and registration", lambda: inputs_section(campus, wd, truth)),
        _guarded("Patch counts and their fit", lambda: histogram_section(wd)),
        _guarded("Class map", lambda: class_map_section(wd, grid, origin)),
        _guarded("Stages: time and memory", lambda: stages_section(wd)),
    ]
    region_sec = _guarded("Rebuilt regions: before and after", regions_fn)
    if quality:
        sections.append(_guarded("Quality against the truth", lambda: quality_section(
            wd, truth, origin, tiles, bool(regions and regions[0]))))
    sections += [region_sec, _guarded("Output: 3D Tiles", lambda: output_section(wd))]
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    page = render_page(f"ms3d run report: {campus.get('name', cfg.name)}",
                       f"work dir {wd.root} · ms3d {campus.get('code_version', '?')} · written {now}", sections)
    path = wd.root / "output" / "report.html"
    write_bytes_atomic(path, page.encode())
    figures = [name for s in sections for name in s.figures]
    return {"report": str(path), "figures": figures, "sections": [s.title for s in sections],
            "bytes": len(page), "truth": str(truth) if truth else None, "seconds": time.perf_counter() - t0}
