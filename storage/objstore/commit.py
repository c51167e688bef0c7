"""A commit protocol that needs no rename: a unit's outputs become visible only through its record.

::

    objects/{stage}/{unit}/{token}/{name}    the outputs of one attempt (token: a fresh uuid per attempt)
    records/{stage}/{unit}.json              the unit's record: logical name -> key, size, sha256 (, etag)

:func:`put_unit_outputs` writes every object first and the record last; the record is one small object
written by one PUT (atomic on S3; renamed into place locally), so it is the commit point. A unit killed
before it leaves objects that nothing names: :func:`resolve` trusts only recorded keys, and
:func:`sweep_unrecorded` deletes unreferenced objects once they are older than a grace age (so the
objects of a unit being written right now, whose record is not there yet, survive). A re-run of a unit
writes under a new token and replaces the record; the previous attempt's objects are swept the same way.
"""

from __future__ import annotations

import hashlib
import json
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from storage.errors import InputError
from storage.objstore.pool import first_error, io_map
from storage.objstore.store import Store, check_key

OBJECTS, RECORDS = "objects", "records"
RECORD_VERSION = 1
DEFAULT_GRACE_S = 3600.0


@dataclass(frozen=True)
class OutputRef:
    """One recorded output: its object key (relative to the store root), size in bytes, sha256 hex."""

    key: str
    size: int
    sha256: str
    etag: str | None = None


@dataclass(frozen=True)
class UnitRecord:
    """The commit record of one (stage, unit): ``files`` maps logical name -> :class:`OutputRef`."""

    stage: str
    unit: str
    token: str
    files: dict[str, OutputRef]
    written_utc: float
    meta: dict | None = None  # JSON-able facts committed with the outputs (fingerprint, params hash, ...)

    def to_json(self) -> dict:
        return {"version": RECORD_VERSION, "stage": self.stage, "unit": self.unit, "token": self.token,
                "written_utc": self.written_utc,
                "files": {n: {k: v for k, v in vars(r).items() if v is not None} for n, r in self.files.items()},
                "meta": self.meta or {}}

    @classmethod
    def from_json(cls, d: dict) -> UnitRecord:
        return cls(stage=d["stage"], unit=d["unit"], token=d["token"], written_utc=float(d["written_utc"]),
                   files={n: OutputRef(**r) for n, r in d["files"].items()}, meta=d.get("meta") or None)


def record_key(stage: str, unit: str) -> str:
    _check_id(stage, "stage")
    _check_id(unit, "unit")
    return f"{RECORDS}/{stage}/{unit}.json"


def _check_id(value: str, what: str) -> None:
    if not value or "/" in value or value in (".", "..") or value.endswith(".json"):
        raise ValueError(f"bad {what} id {value!r}: one non-empty key part without '/'")


def _sha256_file(path: Path) -> tuple[str, int]:
    h, n = hashlib.sha256(), 0
    with open(path, "rb") as f:
        while block := f.read(1 << 22):
            h.update(block)
            n += len(block)
    return h.hexdigest(), n


def put_unit_outputs(store: Store, stage: str, unit: str, files: dict[str, bytes | str | Path],
                     meta: dict | None = None) -> UnitRecord:
    """Write a unit's outputs under a fresh key each, then its record (the commit point).

    Args:
        store: where the work dir lives.
        stage / unit: ids (one key part each, e.g. "partition", "3_-2").
        files: logical name (a relative a/b key, e.g. "points.parquet") -> bytes, or a local file to upload.
        meta: JSON-able facts committed atomically with the outputs (e.g. the manifest row's input
            fingerprint and params hash, so "done" and "its outputs" are one object). Never credentials.
    Returns:
        the record now in force (readers that resolve the unit see exactly these keys).
    """
    rkey = record_key(stage, unit)
    token = uuid.uuid4().hex

    def upload(item: tuple[str, bytes | str | Path]) -> OutputRef:
        name, src = item
        key = f"{OBJECTS}/{stage}/{unit}/{token}/{check_key(name)}"
        if isinstance(src, (bytes, bytearray, memoryview)):
            data = bytes(src)
            etag = store.put(key, data)
            return OutputRef(key, len(data), hashlib.sha256(data).hexdigest(), etag)
        digest, size = _sha256_file(Path(src))
        store.put_file(key, src)
        return OutputRef(key, size, digest, None)

    items = list(files.items())
    done = io_map(upload, items, concurrent=not store.is_local)  # the objects in parallel, the record after all
    if (err := first_error(done)) is not None:
        raise err
    refs = {name: ref for (name, _), ref in zip(items, done)}
    record = UnitRecord(stage, unit, token, refs, time.time(), dict(meta) if meta else None)
    store.put(rkey, json.dumps(record.to_json(), sort_keys=True).encode())
    return record


def resolve(store: Store, stage: str, unit: str) -> UnitRecord | None:
    """The unit's record, or None when it has none (never run, or killed before committing).

    Raises InputError naming the record when it is not a valid record of this (stage, unit)."""
    rkey = record_key(stage, unit)
    try:
        raw = store.get(rkey)
    except FileNotFoundError:
        return None
    try:
        record = UnitRecord.from_json(json.loads(raw))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{store.describe()}: {rkey}", f"not a valid unit record ({exc})") from None
    if (record.stage, record.unit) != (stage, unit):
        raise InputError(f"{store.describe()}: {rkey}", f"records unit {record.stage}/{record.unit}, not {stage}/{unit}")
    return record


def read_output(store: Store, record: UnitRecord, name: str, verify: bool = True) -> bytes:
    """The bytes of one recorded output; with ``verify`` their size and sha256 are checked against the
    record (InputError naming the key when they differ, or when the object is gone)."""
    ref = record.files[name]
    where = f"{store.describe()}: {ref.key}"
    try:
        data = store.get(ref.key)
    except FileNotFoundError:
        raise InputError(where, f"recorded output {name!r} of {record.stage}/{record.unit} is missing") from None
    if verify and (len(data) != ref.size or hashlib.sha256(data).hexdigest() != ref.sha256):
        raise InputError(where, f"recorded output {name!r} does not match its record (size/sha256)")
    return data


def recorded_keys(store: Store) -> set[str]:
    """Every object key named by any unit record of the store."""
    keys = set()
    for info in store.list(RECORDS):
        if not info.key.endswith(".json"):
            continue
        stage, unit = info.key[len(RECORDS) + 1:-len(".json")].split("/", 1)
        record = resolve(store, stage, unit)
        if record is not None:
            keys.update(ref.key for ref in record.files.values())
    return keys


def sweep_unrecorded(store: Store, grace_s: float = DEFAULT_GRACE_S, now: float | None = None) -> list[str]:
    """Delete the objects under ``objects/`` that no record names and that are older than ``grace_s``
    seconds (by the store's modified time). Call while holding the run lock. Returns the deleted keys."""
    now = time.time() if now is None else now
    keep = recorded_keys(store)
    gone = [o.key for o in store.list(OBJECTS) if o.key not in keep and now - o.mtime >= grace_s]
    store.delete(gone)
    return gone
