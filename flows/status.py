"""``ms3d status``: tiles done, empty, failed (stale) and pending, bad inputs, and whether the campus is
complete, from the work dir's campus.json and manifest records."""

from __future__ import annotations

import json
from pathlib import Path

from storage.errors import InputError
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import all_records


def campus_status(work_dir: str) -> dict:
    wd = WorkDir(work_dir)
    if not wd.root.exists():
        raise InputError(wd.root, "no such work dir")
    if not wd.campus_json.exists() and not wd.manifest_dir.exists():
        raise InputError(wd.root, "not an ms3d work dir (no campus.json): run `ms3d run CONFIG` first")
    recs = all_records(wd)
    part = {r.unit: r for r in recs if r.stage == "partition"}
    staged = {t.key for t in wd.staged_tiles()}
    try:
        campus = json.loads(wd.campus_json.read_text())
    except (OSError, json.JSONDecodeError):
        campus = {}
    inputs = campus.get("inputs", [])
    bad = {r["path"]: r["error"] for r in inputs if r.get("error")}
    bad |= {r.unit: r.error for r in recs if r.stage == "ingest" and r.status == "failed"}
    incomplete = [r["path"] for r in inputs if r.get("error") and not (r.get("lo") and r.get("hi"))]
    return {
        "work_dir": str(wd.root),
        "done": sorted(k for k, r in part.items() if r.status == "done"),
        "empty": sorted(k for k, r in part.items() if r.status == "empty"),
        "failed": {k: r.error for k, r in sorted(part.items()) if r.status == "failed"},
        "stale": sorted(t.key for t in wd.stale_tiles()),
        "pending": sorted(staged - set(part)),
        "bad_inputs": bad,
        "incomplete": incomplete,
        "skipped_files": campus.get("skipped_files", []),
        "registered": any(r.stage == "register" and r.status == "done" for r in recs)
        or (wd.root / "registration.json").exists(),
        "registration": (campus.get("registration") or {}).get("method"),
    }


def format_status(st: dict) -> str:
    lines = [f"work dir {st['work_dir']}",
             f"registration: {st['registration'] or ('yes' if st['registered'] else 'not yet')}",
             (f"tiles: {len(st['done'])} done, {len(st['empty'])} empty, {len(st['failed'])} failed, "
              f"{len(st['pending'])} pending")]
    for k, err in st["failed"].items():
        stale = " (keeps its last good store, marked stale)" if k in st["stale"] else ""
        lines.append(f"  FAILED {k}{stale}: {err}")
    for k, err in st["bad_inputs"].items():
        lines.append(f"  bad input {Path(k).name}: {err}")
    if st["incomplete"]:
        lines.append(f"  the campus is INCOMPLETE: {len(st['incomplete'])} input(s) of unknown extent are missing "
                     "from every tile: " + ", ".join(Path(p).name for p in st["incomplete"][:10]))
    if st["skipped_files"]:
        lines.append(f"  {len(st['skipped_files'])} file(s) skipped in input folders: "
                     + ", ".join(Path(p).name for p, _ in st["skipped_files"][:10]))
    if st["pending"]:
        lines.append("  pending: " + ", ".join(st["pending"][:30]) + (" ..." if len(st["pending"]) > 30 else ""))
    return "\n".join(lines)


def status_exit_code(st: dict) -> int:
    """0 when every tile is done or empty and the campus is complete, else 1."""
    return 0 if not (st["failed"] or st["incomplete"] or st["bad_inputs"] or st["pending"]) else 1
