"""The run manifest: one row per (stage, unit) with fingerprints, status, error, seconds and outputs.

Tasks run on many Dask workers at once, so each writes its own small JSON record atomically under
``manifest.d/{stage}/{unit}.json``; no two writers ever touch one file. The flow consolidates the
records into ``manifest.parquet`` (a snapshot for people and tools) after each stage.

A unit is *done* when its record says ``done`` with the same input fingerprint and parameter hash
and its outputs exist. A re-run skips done units and redoes failed or changed ones.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from storage import recorded
from storage.atomic import atomic_path, write_json_atomic
from storage.workdir.layout import WorkDir

STATUSES = ("done", "failed", "empty", "skipped")


@dataclass
class ManifestRecord:
    stage: str
    unit: str
    status: str  # one of STATUSES
    fingerprint: str = ""
    params_hash: str = ""
    error: str = ""
    seconds: float = 0.0
    outputs: list[str] = field(default_factory=list)
    summary: dict = field(default_factory=dict)
    updated_at: float = 0.0


def params_hash(params: dict) -> str:
    """Stable hash of a JSON-able parameter dict."""
    return hashlib.sha256(json.dumps(params, sort_keys=True, default=str).encode()).hexdigest()[:16]


def combine_fingerprints(parts: list[str]) -> str:
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:32]


def _record_path(wd: WorkDir, stage: str, unit: str) -> Path:
    return wd.manifest_dir / stage / f"{unit}.json"


def write_record(wd: WorkDir, rec: ManifestRecord) -> None:
    rec.updated_at = time.time()
    write_json_atomic(_record_path(wd, rec.stage, rec.unit), asdict(rec))


def read_record(wd: WorkDir, stage: str, unit: str) -> ManifestRecord | None:
    p = _record_path(wd, stage, unit)
    try:
        return ManifestRecord(**json.loads(p.read_text()))
    except (FileNotFoundError, json.JSONDecodeError, TypeError):
        return None


def read_stage_records(wd: WorkDir, stage: str) -> dict[str, ManifestRecord]:
    """Every readable record of ``stage`` in one pass over ``manifest.d/{stage}/``: {unit: record}.

    The planner's one manifest read per stage (``tasks.units.pending_units``): a directory listing and
    one small JSON read per record, no per-unit path probing. An unreadable record (foreign, or a
    truncated file from outside ms3d) is left out, i.e. its unit is treated as not done.
    """
    out: dict[str, ManifestRecord] = {}
    try:
        entries = os.scandir(wd.manifest_dir / stage)
    except (FileNotFoundError, NotADirectoryError):
        return out
    with entries:
        for e in entries:
            if e.name.startswith(".") or not e.name.endswith(".json"):
                continue  # ".name.XXXX.tmp.json": a record being written (storage.atomic), not yet one
            try:
                with open(e.path, "rb") as f:
                    rec = ManifestRecord(**json.loads(f.read()))
            except (OSError, ValueError, TypeError):
                continue
            if rec.stage == stage:
                out[rec.unit] = rec
    return out


def record_is_current(wd: WorkDir, rec: ManifestRecord | None, fingerprint: str, phash: str) -> bool:
    """Whether ``rec`` marks its unit done (or empty) for these fingerprints, with every output on disk (on a
    bucket: recorded, maybe not downloaded)."""
    return redo_reason(wd, rec, fingerprint, phash) == ""


def redo_reason(wd: WorkDir, rec: ManifestRecord | None, fingerprint: str, phash: str) -> str:
    """Why a unit with record ``rec`` is not current (one phrase; "" when it is): shown in its new record's
    summary (``redo``), so a rerun that redid a unit says what changed."""
    if rec is None:
        return "no record"
    if rec.status not in ("done", "empty"):
        return f"last run {rec.status}"
    if rec.params_hash != phash:
        return "parameters changed"
    if rec.fingerprint != fingerprint:
        return "inputs changed"
    missing = [o for o in rec.outputs if not recorded.exists(wd.root / o)]
    return f"output missing: {missing[0]}" if missing else ""


def is_done(wd: WorkDir, stage: str, unit: str, fingerprint: str, phash: str) -> ManifestRecord | None:
    """The done record of a unit when it matches the fingerprints and its outputs exist, else None."""
    rec = read_record(wd, stage, unit)
    return rec if record_is_current(wd, rec, fingerprint, phash) else None


def all_records(wd: WorkDir) -> list[ManifestRecord]:
    out = []
    if not wd.manifest_dir.exists():
        return out
    for p in sorted(wd.manifest_dir.glob("*/*.json")):
        try:
            out.append(ManifestRecord(**json.loads(p.read_text())))
        except (json.JSONDecodeError, TypeError):
            continue  # a record is written atomically; an unreadable one is foreign and ignored
    return out


def consolidate(wd: WorkDir) -> Path:
    """Write manifest.parquet from the per-unit records (atomically)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    recs = all_records(wd)
    cols = {
        "stage": [r.stage for r in recs],
        "unit": [r.unit for r in recs],
        "status": [r.status for r in recs],
        "fingerprint": [r.fingerprint for r in recs],
        "params_hash": [r.params_hash for r in recs],
        "error": [r.error for r in recs],
        "seconds": pa.array([r.seconds for r in recs], pa.float64()),
        "outputs": [json.dumps(r.outputs) for r in recs],
        "summary": [json.dumps(r.summary, default=str) for r in recs],
        "updated_at": pa.array([r.updated_at for r in recs], pa.float64()),
    }
    table = pa.table(cols)
    with atomic_path(wd.manifest) as tmp:
        pq.write_table(table, tmp)
    return wd.manifest
