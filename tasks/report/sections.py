"""The run report's sections, each rendered from what the work dir holds (paths, records, figures): no
manifest or work-dir access here (``stage.py`` gathers and writes)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

from storage.grid import PatchGrid
from storage.patches.read import PatchStore
from tasks.report.figures import class_map_png
from tasks.report.html import Section, esc, table


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


def inputs_section(campus: dict, root: Path, truth: Path | None) -> Section:
    """Inputs, frame and grid from ``campus.json`` (``campus``), the registration recorded in
    ``root/registration.json`` and, with a synth campus folder ``truth``, its error against the true one."""
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
    recorded = root / "registration.json"
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
        if "verdict" in reg:  # tasks.register.guard: what the applied transform does at the data
            body += table(["verdict", "displacement p50 (m)", "displacement max (m)", "distance before (m)",
                           "distance after (m)"], [[reg["verdict"].get("reason"), reg.get("displacement_p50_m"),
                           reg.get("displacement_max_m"), reg.get("distance_before_m"), reg.get("distance_after_m")]])
            if reg.get("warning"):
                body += f"<p><b>warning:</b> {esc(reg['warning'])}</p>"
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


def histogram_section(records: list, report_dir: Path) -> Section:
    """The outlier stage's fit (its manifest record among ``records``) and its histograms in ``report_dir``."""
    sec = Section("Patch counts and their fit")
    out = next((r.summary for r in records if r.stage == "outliers"), None)
    if out:
        rows = [[name, out[name]["mean_log10"], out[name]["std_log10"], out[name]["low"], out[name]["high"],
                 out[name]["flagged"]] for name in ("points", "faces") if name in out]  # fmt: skip
        sec.body += table(["per patch", "mean log10", "sd log10", "kept from", "kept to", "flagged"], rows)
    for p in sorted(report_dir.glob("patch_*_histogram.png")):
        sec.figures[p.stem] = p.read_bytes()
    if not sec.figures:
        sec.body += "<p>No histograms (the outlier stage has not run).</p>"
    return sec


def class_map_section(tile_dirs: list[Path], grid: PatchGrid, origin: np.ndarray) -> Section:
    """A top view of the patches of the stores in ``tile_dirs`` coloured by classify's score, else by grade
    (the labels): figure "class_map". origin: (3,) float64 world metres of the campus frame."""
    sec = Section("Class map")
    ii, jj, vals, kinds = [], [], [], set()
    for tile_dir in tile_dirs:
        store = PatchStore(tile_dir)
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
    sec.figures["class_map"] = png
    n_bad = int((value >= 0.5).sum()) if kind == "score" else int((value == 1).sum())
    sec.body = (f"<p>Each pixel is a column of patches (the worst over height) coloured by "
                f"{'score' if kind == 'score' else 'grade'} ({esc(src)}): {n_bad:,} of {len(value):,} patches bad.</p>")
    return sec


def stages_section(records: list) -> Section:
    """Units, status, seconds and peak RSS per stage from the manifest ``records`` (ManifestRecord)."""
    by_stage: dict[str, list] = {}
    for r in records:
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


def quality_section(truth: Path | None, tiles: list[str], figures: Callable[[], dict], any_rebuilt: bool) -> Section:
    """The quality figures (``figures()``: the quality stage's ``report/quality.json`` document), or why
    there are none (no truth, no merged tile)."""
    sec = Section("Quality against the truth")
    if truth is None:
        sec.body = "<p>No truth for these inputs (quality is measured on synth campuses only).</p>"
        return sec
    if not tiles:
        sec.body = "<p>No merged tiles yet.</p>"
        return sec
    cache = figures()
    key = cache["key"]
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
    sec.body += (f"<p>Surfaces sampled every {key['spacing_m'] * 100:g} cm, evaluated in {key['tile_m']:g} m tiles "
                 f"(distances capped at {key['buffer_m']:g} m); uncovered: facade area of the truth with no "
                 "surface within 20 cm along its normal.</p>")
    if not any_rebuilt:
        sec.body += "<p>No region was rebuilt: the merged model is the input mesh, retained whole.</p>"
    return sec


def output_section(out: Path) -> Section:
    """What the export wrote in the work dir's ``output/`` folder ``out``, with links and the ``ms3d view``
    command."""
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
    body += (f"<p>Open the model in a browser: <code>ms3d view {esc(out.parent)}</code> "
             "(serves this folder's <code>output/</code> on localhost with the viewer page; colour by grade, "
             "source or region and click a face for its provenance).</p>")
    return Section("Output: 3D Tiles", body)

