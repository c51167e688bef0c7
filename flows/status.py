"""``ms3d status``: tiles done, failed and pending, from the work dir's manifest records."""

from __future__ import annotations

from storage.manifest import all_records
from storage.workdir import WorkDir


def campus_status(work_dir: str) -> dict:
    """{"done": [...], "empty": [...], "failed": {tile: error}, "pending": [...], "ingest_failed": {...}}."""
    wd = WorkDir(work_dir)
    recs = all_records(wd)
    part = {r.unit: r for r in recs if r.stage == "partition"}
    staged = {t.key for t in wd.staged_tiles()}
    return {
        "work_dir": str(wd.root),
        "done": sorted(k for k, r in part.items() if r.status == "done"),
        "empty": sorted(k for k, r in part.items() if r.status == "empty"),
        "failed": {k: r.error for k, r in sorted(part.items()) if r.status == "failed"},
        "pending": sorted(staged - set(part)),
        "ingest_failed": {r.unit: r.error for r in recs if r.stage == "ingest" and r.status == "failed"},
        "registered": any(r.stage == "register" and r.status == "done" for r in recs),
    }


def format_status(st: dict) -> str:
    lines = [f"work dir {st['work_dir']}",
             f"registered: {'yes' if st['registered'] else 'no'}",
             (f"tiles: {len(st['done'])} done, {len(st['empty'])} empty, {len(st['failed'])} failed, "
              f"{len(st['pending'])} pending")]
    for k, err in st["failed"].items():
        lines.append(f"  FAILED {k}: {err}")
    for k, err in st["ingest_failed"].items():
        lines.append(f"  ingest {k} failed: {err}")
    if st["pending"]:
        lines.append("  pending: " + ", ".join(st["pending"][:30]) + (" ..." if len(st["pending"]) > 30 else ""))
    return "\n".join(lines)
