"""The run summary: what this run did and did not do, and the error raised when some units failed."""

from __future__ import annotations

from storage.workdir.layout import WorkDir
from storage.workdir.manifest import all_records


class CampusRunFailed(RuntimeError):
    """Some units failed or some inputs could not be placed; the others are done and the manifest says which."""

    def __init__(self, summary: dict):
        self.summary = summary
        failed = summary["failed"]
        lines = []
        if failed:
            lines.append(f"{len(failed)} unit(s) failed:")
            groups: dict[str, list[str]] = {}
            for unit, err in failed.items():  # tiles blocked by one input share one line
                groups.setdefault(err, []).append(unit)
            for err, units in list(groups.items())[:20]:
                names = ", ".join(units[:6]) + (f" and {len(units) - 6} more" if len(units) > 6 else "")
                lines.append(f"  {names}: {err}")
            if len(groups) > 20:
                lines.append(f"  ... and {len(groups) - 20} more errors (ms3d status {summary['work_dir']})")
        if summary.get("incomplete"):
            lines.append(f"the campus is INCOMPLETE: {len(summary['incomplete'])} input(s) of unknown extent "
                         "could not be read, so no tile holds their data")
        super().__init__("\n".join(lines))

    def __reduce__(self):
        return (type(self), (self.summary,))


def _stage_counts(results: list[dict]) -> dict:
    """Counts of units run / skipped / failed by this run, and the names of those run."""
    out = {"run": 0, "skipped": 0, "failed": 0, "units_run": []}
    for r in results:
        if r.get("status") == "failed":
            out["failed"] += 1
        elif r.get("skipped"):
            out["skipped"] += 1
        else:
            out["run"] += 1
            out["units_run"].append(r.get("unit"))
    out["units_run"].sort()
    return out


def summarise(wd: WorkDir, wall_s: float, failed: dict, outliers: dict, since: float = 0.0, stages=None,
              incomplete=(), skipped_files=(), registration=None) -> dict:
    recs = all_records(wd)
    tiles = [r for r in recs if r.stage == "partition"]
    stale = {t.key for t in wd.stale_tiles()}
    task_s = sum(r.seconds for r in recs if r.updated_at >= since)  # work done by this run only
    reg = registration or {}
    return {
        "work_dir": str(wd.root),
        "wall_seconds": wall_s,
        "task_seconds": task_s,
        "stages": {name: _stage_counts(res) for name, res in (stages or {}).items()},
        "tiles_done": sorted(r.unit for r in tiles if r.status == "done"),
        "tiles_empty": sorted(r.unit for r in tiles if r.status == "empty"),
        "tiles_failed": sorted(r.unit for r in tiles if r.status == "failed"),
        "tiles_stale": sorted(stale),
        "tile_rows": [{"tile": r.unit, "status": r.status, "points": r.summary.get("n_points", 0),
                       "faces": r.summary.get("n_faces", 0), "patches": r.summary.get("n_patches", 0),
                       "seconds": round(r.seconds, 2), "error": r.error[:200]} for r in tiles],
        "failed": failed,
        "incomplete": list(incomplete),
        "skipped_files": [list(s) for s in skipped_files],
        "registration": {k: reg.get(k) for k in ("method", "scale", "fitness", "reused", "check", "warning",
                                                 "verdict", "displacement_p50_m", "displacement_max_m",
                                                 "distance_before_m", "distance_after_m") if k in reg},
        "outliers": outliers,
        "grades": grades_summary(wd),
        "repair": repair_summary(recs),
        "holdout": holdout_summary(wd),
        "input_warnings": input_warnings(wd),
    }


REPAIR_COUNTS = ("zone_faces", "replaced_faces", "rebuilt_faces", "kept_agreeing_faces", "unsupported_faces_dropped",
                 "input_faces_restored")


def repair_summary(recs) -> dict:
    """What the repair did over the current region records: {"regions": n done, and the sum of each of
    REPAIR_COUNTS} (the faces of the graded-bad zones, those replaced, rebuilt, kept because the scan agrees
    with them, rebuilt faces dropped as unsupported chords, input faces put back under them)."""
    done = [r for r in recs if r.stage == "region" and r.status == "done"]
    return {"regions": len(done), **{k: int(sum((r.summary or {}).get(k, 0) or 0 for r in done)) for k in REPAIR_COUNTS}}


def repair_line(rep: dict | None) -> str:
    """One line of the repair counts ("" when no region was repaired).

    >>> repair_line({"regions": 2, "zone_faces": 90, "replaced_faces": 40, "rebuilt_faces": 55, "kept_agreeing_faces": 50,
    ...              "unsupported_faces_dropped": 3, "input_faces_restored": 4})
    'repair: 2 regions, 40 of their 90 faces replaced by 55 rebuilt (50 kept: the scan agrees with them); 3 unsupported rebuilt faces dropped, 4 input faces kept where the rebuild left nothing'
    """
    if not rep or not rep.get("regions"):
        return ""
    return (f"repair: {rep['regions']} regions, {rep['replaced_faces']} of their {rep['zone_faces']} faces replaced by "
            f"{rep['rebuilt_faces']} rebuilt ({rep['kept_agreeing_faces']} kept: the scan agrees with them); "
            f"{rep['unsupported_faces_dropped']} unsupported rebuilt faces dropped, {rep['input_faces_restored']} "
            "input faces kept where the rebuild left nothing")


def holdout_summary(wd: WorkDir) -> dict:
    """The held-out MLS strips' campus figures of ``report/holdout.json`` (the quality stage's):
    {"held_out", "points", "holdout", "campus": {model: figures}, "buildings": how many hold held-out points
    (where the file has buildings)}, or {} when there are none."""
    from tasks.quality import read_heldout

    doc = read_heldout(wd) or {}
    out = {k: doc[k] for k in ("held_out", "points", "held_out_share", "holdout", "campus") if k in doc}
    if "buildings" in doc:
        out["buildings"] = sum(1 for b in doc["buildings"] if b.get("id"))
    return out


def holdout_line(h: dict | None) -> str:
    """One line of the held-out figures, or "".

    >>> holdout_line({"held_out": 1200, "campus": {"input mesh": {"median_m": 0.031, "p90_m": 0.12, "within_5cm": 0.7,
    ...     "within_10cm": 0.88}, "merged model": {"median_m": 0.012, "p90_m": 0.05, "within_5cm": 0.9, "within_10cm": 0.97}}})
    'held-out MLS (1,200 points): input mesh median 3.1 cm, p90 12.0 cm, 70% within 5 cm; merged model median 1.2 cm, p90 5.0 cm, 90% within 5 cm'
    >>> holdout_line({"held_out": 1200, "buildings": 14, "campus": {"merged model": {"median_m": 0.012, "p90_m": 0.05,
    ...     "within_5cm": 0.9, "within_10cm": 0.97}}})
    'held-out MLS (1,200 points, 14 buildings): merged model median 1.2 cm, p90 5.0 cm, 90% within 5 cm'
    """
    if not h or not h.get("campus"):
        return ""
    parts = [f"{m} median {100 * f['median_m']:.1f} cm, p90 {100 * f['p90_m']:.1f} cm, {100 * f['within_5cm']:.0f}% within 5 cm"
             for m, f in h["campus"].items() if f.get("median_m") is not None]
    where = f", {h['buildings']:,} building{'s' * (h['buildings'] != 1)}" if "buildings" in h else ""
    return f"held-out MLS ({h['held_out']:,} points{where}): " + "; ".join(parts) if parts else ""


def input_warnings(wd: WorkDir) -> list[str]:
    """What the readers worked around in the inputs of campus.json (``InputFile.warnings``), one line each."""
    import json

    doc = json.loads(wd.campus_json.read_text()) if wd.campus_json.exists() else {}
    return [w for rec in doc.get("inputs") or [] for w in rec.get("warnings") or []]


def grades_summary(wd: WorkDir) -> dict:
    """Patches by grade and unknown reason over the live stores (``tasks.report.census_of_stores``), with
    the thresholds of the config snapshot in ``campus.json`` (``partition.min_faces`` / ``min_points``,
    ``report.max_unknown_share``); {} when there is no store or no campus."""
    from storage.workdir.layout import read_campus
    from tasks.config.campus import ReportConfig
    from tasks.report import census_of_stores

    tiles = wd.live_tiles()
    if not tiles or not wd.campus_json.exists():
        return {}
    snap = read_campus(wd).get("config") or {}
    part, rep = snap.get("partition") or {}, snap.get("report") or {}
    census = census_of_stores([wd.tile_dir(t) for t in tiles], part.get("min_faces", 1), part.get("min_points", 1))
    return census.to_json() | {"max_unknown_share": rep.get("max_unknown_share", ReportConfig().max_unknown_share)}


def unknown_warning(grades: dict | None) -> str:
    """One warning line when more than ``max_unknown_share`` of the patches are unknown, else "".

    >>> unknown_warning({"patches": 10, "unknown": 7, "unknown_share": 0.7, "max_unknown_share": 0.5,
    ...                  "reasons": {"no_faces": 5, "no_points": 1, "too_few": 0, "not_graded": 1}})
    'WARNING: 70% of the 10 patches could not be graded (no faces 5, no points 1, not graded 1); over report.max_unknown_share 0.5: see report.html'
    """
    if not grades or not grades.get("patches") or grades["unknown_share"] <= grades["max_unknown_share"]:
        return ""
    why = ", ".join(f"{k.replace('_', ' ')} {n:,}" for k, n in grades["reasons"].items() if n)
    return (f"WARNING: {100 * grades['unknown_share']:.0f}% of the {grades['patches']:,} patches could not be graded "
            f"({why}); over report.max_unknown_share {grades['max_unknown_share']:g}: see report.html")


def format_summary(s: dict) -> str:
    lines = [f"work dir: {s['work_dir']}"]
    reg = s.get("registration") or {}
    if reg:
        lines.append("registration: " + reg.get("method", "?") + (" (reused)" if reg.get("reused") else ""))
        if reg.get("warning"):
            lines.append("warning: " + reg["warning"])
    for name, c in (s.get("stages") or {}).items():
        lines.append(f"{name}: {c['run']} run, {c['skipped']} unchanged (skipped), {c['failed']} failed")
    lines.append(f"tiles: {len(s['tiles_done'])} done, {len(s['tiles_empty'])} empty, "
                 f"{len(s['tiles_failed'])} failed" + (f" ({len(s['tiles_stale'])} keep a stale store)"
                                                       if s.get("tiles_stale") else ""))
    if s.get("skipped_files"):
        lines.append(f"skipped {len(s['skipped_files'])} file(s) in input folders: "
                     + ", ".join(f"{p.rsplit('/', 1)[-1]} ({why})" for p, why in s["skipped_files"][:5])
                     + (" ..." if len(s["skipped_files"]) > 5 else ""))
    lines += [f"warning: {w}" for w in s.get("input_warnings") or []]
    lines += [w for w in [unknown_warning(s.get("grades")), repair_line(s.get("repair")),
                          holdout_line(s.get("holdout"))] if w]
    lines.append(f"wall {s['wall_seconds']:.1f} s, sum of task times {s['task_seconds']:.1f} s")
    out = s.get("output") or {}
    if out.get("tileset"):
        lines.append(f"3D Tiles: {out['tileset']}  (view: ms3d view {s['work_dir']})")
    if out.get("report"):
        lines.append(f"report:   {out['report']}")
    return "\n".join(lines)
