"""The run report: ``output/report.html``, one self-contained page per run (figures embedded as PNG data).

Sections, each from what the work dir holds (a section whose inputs are missing says so):

1. inputs and registration: ``campus.json`` (inputs, CRS, origin, grid), the recorded transform
   (``registration.json``) as rotation / scale / translation with its fitness and RMSE, and, for a synth
   campus, its error against the true transform;
2. the patch-count histograms with their normal fit (``report/patch_*_histogram.png``, outlier stage);
3. the class map: a top view of the patches coloured by score (classify's ``grades``), else by grade
   (the labels), written to ``report/class_map.png`` too; then the grade distribution (good / bad /
   unknown), why patches are unknown (no faces, no points, too few) and the score histogram
   (``grades.py``, ``report/score_histogram.png``), which need no truth;
4. per-stage units, times and peak memory from the manifest records (``manifest.d``);
5. quality against the truth where it exists (a synth campus): the merged model, and the input mesh
   when regions were rebuilt (cached in ``report/quality.json`` by the merged tiles' fingerprints); then
   accuracy without truth: the held-out MLS strips against the input mesh and the merged model, for the
   campus and per tile (``report/holdout.json``, the quality stage's; ``heldout.py``);
6. before/after renders of the rebuilt regions (``report/regions/*.png``), when there are any;
7. the output: links to the tileset, overview and georeference, and the ``ms3d view`` command.

The sections render (``sections.py``, ``regions.py``); the quality figures come from the quality stage
(``tasks.quality``). The stage :func:`run_report` reads only small tables, the merged tiles (one at a time, for quality and
region renders) and the patches of the regions it renders.
"""

from __future__ import annotations

import datetime
import json
import logging
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

from storage import __version__, recorded
from storage.atomic import file_sha256, write_bytes_atomic, write_json_atomic
from storage.errors import InputError
from storage.workdir.layout import WorkDir, campus_frame, read_campus
from storage.workdir.manifest import all_records, combine_fingerprints, is_done, params_hash
from tasks.classify import grading_threshold
from tasks.quality import ensure_quality, merged_tiles, read_heldout, truth_dir_of
from tasks.report.grades import census_of_stores, grades_section
from tasks.report.heldout import heldout_section
from tasks.report.html import Section, esc, render_page
from tasks.report.regions import regions_section
from tasks.report.sections import (
    class_map_section,
    histogram_section,
    inputs_section,
    output_section,
    quality_section,
    stages_section,
)
from tasks.units import MustRun, is_planning, record_step, skipped_summary

log = logging.getLogger("ms3d.report")


def _guarded(title: str, fn: Callable[[], Section]) -> Section:
    """A section, or a note saying why it could not be made (the report never fails for one section)."""
    try:
        return fn()
    except (InputError, OSError, ValueError, KeyError) as e:
        log.warning("report section %r: %s", title, e)
        return Section(title, f"<p class='note'>Could not make this section: {esc(e)}</p>")


def _written(sec: Section, folder: Path) -> Section:
    """``sec`` after writing its figures to ``folder/<name>.png``."""
    for name, png in sec.figures.items():
        write_bytes_atomic(folder / f"{name}.png", png)
    return sec


REGIONS_VERSION = 1  # bumped whenever the region renders change for the same inputs
_REGION_INPUTS = ("partition", "classify", "merge")  # what the renders read: stores, grades, merged tiles


def _regions_key(records: list, tiles: list[str], grid_json: dict) -> str:
    """What the region renders depend on: the store, grade and merged-tile records of ``tiles``, the grid."""
    parts = [json.dumps([r.stage, r.unit, r.fingerprint, r.params_hash]) for r in records
             if r.stage in _REGION_INPUTS and r.unit in tiles]
    return combine_fingerprints(sorted(parts) + [json.dumps([REGIONS_VERSION, tiles, grid_json], sort_keys=True)])


def _regions_doc(cfg, wd: WorkDir, records: list | None) -> tuple[dict, str, list[str]]:
    """(the kept ``section.json`` or {}, the key of the current inputs, the merged tiles)."""
    tiles = merged_tiles(wd)
    key = _regions_key(records if records is not None else all_records(wd), tiles, cfg.grid().to_json())
    path = wd.report_dir / "regions" / "section.json"
    doc = json.loads(path.read_text()) if path.exists() else {}
    if doc.get("key") != key or not all(recorded.is_file(path.parent / f"{n}.png") for n in doc.get("figures", [])):
        doc = {}
    return doc, key, tiles


def region_renders_fresh(cfg, wd: WorkDir) -> bool:
    """Whether the kept region renders match the work dir's current inputs (nothing to draw)."""
    return bool(_regions_doc(cfg, wd, None)[0])


def region_renders(cfg, wd: WorkDir, records: list | None = None) -> tuple[Section, bool]:
    """The rebuilt regions' section and whether any region was rebuilt, drawn once per input state: the
    renders go to ``report/regions/*.png`` with ``section.json`` (its key, body and figure names), and a later
    call with the same inputs reads them back. The flow draws them beside the export; the report reuses them."""
    doc, key, tiles = _regions_doc(cfg, wd, records)
    folder = wd.report_dir / "regions"
    if doc:
        return Section(doc["title"], doc["body"], {n: (folder / f"{n}.png").read_bytes() for n in doc["figures"]}), \
            bool(doc["any_rebuilt"])
    sec, any_rebuilt = regions_section(wd.root / "tiles", tiles, cfg.grid(), campus_frame(read_campus(wd)).origin_array)
    _written(sec, folder)
    write_json_atomic(folder / "section.json", {"key": key, "title": sec.title, "body": sec.body, "figures": list(sec.figures),
                                 "any_rebuilt": bool(any_rebuilt)})
    return sec, any_rebuilt


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
    records = all_records(wd)
    regions: list[bool] = []

    def regions_fn() -> Section:
        sec, any_rebuilt = region_renders(cfg, wd, records)
        regions.append(any_rebuilt)
        return sec

    sections = [
        _guarded("Inputs and registration", lambda: inputs_section(campus, wd.root, truth)),
        _guarded("Patch counts and their fit", lambda: histogram_section(records, wd.report_dir)),
        _guarded("Class map", lambda: _written(class_map_section([wd.tile_dir(t) for t in wd.live_tiles()], grid,
                                                                  origin), wd.report_dir)),
        _guarded("Grades: distribution and unknown patches", lambda: _written(grades_section(
            census_of_stores([wd.tile_dir(t) for t in wd.live_tiles()], cfg.partition.min_faces,
                             cfg.partition.min_points), cfg.partition.min_faces, cfg.partition.min_points,
            grading_threshold(cfg.classify), cfg.report.max_unknown_share), wd.report_dir)),
        _guarded("Stages: time and memory", lambda: stages_section(records)),
    ]
    region_sec = _guarded("Rebuilt regions: before and after", regions_fn)
    if quality:
        rebuilt = bool(regions and regions[0])
        sections.append(_guarded("Quality against the truth", lambda: quality_section(
            truth, tiles, lambda: ensure_quality(wd, truth, origin, tiles, rebuilt, cfg.report.quality_spacing_m), rebuilt)))
    sections.append(_guarded("Accuracy without truth: held-out MLS strips", lambda: heldout_section(read_heldout(wd))))
    sections += [region_sec, _guarded("Output: 3D Tiles", lambda: output_section(wd.output_dir))]
    now = datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC")
    page = render_page(f"ms3d run report: {campus.get('name', cfg.name)}",
                       f"work dir {wd.root} · ms3d {campus.get('code_version', '?')} · written {now}", sections)
    path = wd.report_html
    write_bytes_atomic(path, page.encode())
    figures = [name for s in sections for name in s.figures]
    return {"report": str(path), "figures": figures, "sections": [s.title for s in sections],
            "bytes": len(page), "truth": str(truth) if truth else None, "seconds": time.perf_counter() - t0}


# stages recorded by record_step on every run they make: their seconds change on each run
_ALWAYS_RECORDED = ("export", "quality", "holdout", "outliers", "regions")
REPORT_VERSION = 1  # bumped whenever report.html changes for the same inputs


def _sha(path) -> str:
    try:
        return file_sha256(path)
    except OSError:
        return "-"


def report_fingerprint(wd: WorkDir) -> str:
    """What the run report shows: every manifest record but the report's own (status, fingerprint,
    parameters and, for the units skipped by fingerprint, seconds: a unit that ran this run changes it), the
    content of ``tileset.json``, ``report/quality.json`` and ``report/holdout.json``."""
    parts = []
    for r in all_records(wd):
        if r.stage == "report":
            continue
        secs = None if r.stage in _ALWAYS_RECORDED else r.seconds
        parts.append(json.dumps([r.stage, r.unit, r.status, r.fingerprint, r.params_hash, secs, r.error]))
    parts += [_sha(wd.tileset_json), _sha(wd.report_dir / "quality.json"), _sha(wd.report_dir / "holdout.json")]
    return combine_fingerprints(sorted(parts))


def report_params(cfg) -> dict:
    """The run report's parameters (cfg: CampusConfig): the ``report`` and ``partition`` sections, the grid,
    ``classify.threshold`` and the package and report versions (an upgrade that changes the page, with
    :data:`REPORT_VERSION` bumped, redraws it)."""
    return {"code_version": __version__, "report_version": REPORT_VERSION, "report": cfg.report.model_dump(mode="json"),
            "classify_threshold": cfg.classify.threshold,
            "partition": cfg.partition.model_dump(mode="json"), "grid": cfg.grid().to_json()}


def run_report_unit(cfg, wd: WorkDir) -> dict:
    """The run report as one resumable unit ("report", "campus"): skipped while its fingerprint, its
    parameters and ``output/report.html`` stand; {"status", "report": path, ...}."""
    fp, ph = report_fingerprint(wd), params_hash(report_params(cfg))
    page = wd.report_html
    rec = is_done(wd, "report", "campus", fp, ph)
    if rec is not None and recorded.is_file(page):  # on a bucket: recorded, maybe not downloaded
        return {**skipped_summary(rec), "report": str(page)}
    if is_planning():
        raise MustRun("report", "campus")
    return record_step(wd, "report", "campus", partial(run_report, cfg, wd, quality=cfg.report.quality), fp, ph)


def run_region_renders(cfg, wd: WorkDir) -> dict:
    """The rebuilt regions' before/after renders for the report (``report/regions/``, kept under a key of
    their inputs), drawn beside the export: {"status", "figures" | "error"}. A failure costs nothing but
    time: the report draws them itself and says why not."""
    if is_planning():
        return {"status": "skipped"}
    try:
        sec, _ = region_renders(cfg, wd)
    except (InputError, OSError, ValueError, KeyError) as e:
        return {"status": "failed", "error": str(e).splitlines()[0] if str(e) else type(e).__name__}
    return {"status": "done", "figures": len(sec.figures)}
