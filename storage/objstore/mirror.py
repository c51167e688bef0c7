"""A work dir on an object store, used through a local mirror ("sync-through"): each process (the flow's
driver, each Dask worker) keeps its own copy of the recorded work dir, runs the ordinary local code on
it, and publishes what it changed as one commit of :mod:`storage.objstore.commit`.

::

    s3://bucket/prefix/
      records/sync/{seq}.json        one commit: logical file -> object key, size, sha256; meta: each file's
                                     mtime_ns and the files it deleted
      objects/sync/{seq}/{token}/…   the objects of that commit (written before its record)
      .lock.json                     the run lease (storage.objstore.lock)

- **pull** (:meth:`Mirror.pull`): list the records, read the ones this process has not seen, fold them in
  order (a later commit of a file wins; a deletion removes it) and download each file whose local copy
  differs, setting its mtime to the producer's, so mtime-based fingerprints agree in every process. Only
  recorded objects are ever read: an object written by a unit that died before its record is invisible.
- **push** (:meth:`Mirror.push`): every file of the mirror whose (size, mtime) differs from what this
  process last pulled or pushed, and every such file that is gone, as one commit (objects, then the record).
  A task's manifest records (``manifest.d/``) are files like any other, so a unit's outputs and its
  "done" record become visible together, or not at all.

``seq`` is the pusher's clock in ns plus a random suffix: commits of one stage never touch the same file
(units write disjoint outputs), and stages are separated by the driver, so wall-clock order suffices.
"""

from __future__ import annotations

import hashlib
import json
import os
import threading
import time
import uuid
from pathlib import Path

from storage.errors import InputError
from storage.objstore.commit import RECORDS, UnitRecord, put_unit_outputs
from storage.objstore.store import Store

SYNC_STAGE = "sync"
_SKIP_DIRS = ("prefect",)  # the driver's own Prefect database stays local


class Mirror:
    """The local mirror of one remote work dir in this process.

    store: the work dir's Store; root: the local folder. ``known`` maps a relative path to the
    (size, mtime_ns) it had after the last pull or push; ``stats`` counts commits and files moved.
    """

    def __init__(self, store: Store, root: str | Path):
        self.store, self.root = store, Path(root).absolute()
        self.root.mkdir(parents=True, exist_ok=True)
        self.known: dict[str, tuple[int, int]] = {}
        self.seen: set[str] = set()
        self.files: dict[str, tuple[int, int]] = {}  # folded remote state: rel -> (size, mtime_ns)
        self._pending: dict[str, str] = {}  # recorded files not downloaded yet: rel -> object key
        self.refs: dict = {}  # folded remote state: rel -> OutputRef of its current object
        self.last_utc = 0.0  # written_utc of the latest commit folded
        self.lock = threading.RLock()
        self.lease = None  # the run's Lease while the driver holds it (flows.remote.remote_run)
        self.stats = {"pulled_files": 0, "pushed_files": 0, "commits": 0, "records_read": 0}

    # ------------------------------------------------------------------ pull
    def _records(self) -> list[UnitRecord]:
        prefix = f"{RECORDS}/{SYNC_STAGE}"
        new = []
        for info in self.store.list(prefix):
            if not info.key.endswith(".json") or info.key in self.seen:
                continue
            try:
                d = json.loads(self.store.get(info.key))
                new.append(UnitRecord.from_json(d))
            except FileNotFoundError:
                continue
            except (ValueError, KeyError, TypeError) as exc:
                raise InputError(f"{self.store.describe()}: {info.key}", f"not a valid sync record ({exc})") from None
            self.seen.add(info.key)
        self.stats["records_read"] += len(new)
        return sorted(new, key=lambda r: (r.written_utc, r.unit))

    def pull(self, only=None) -> int:
        """Bring the mirror up to the recorded state (``only``: a predicate on relative paths limiting what
        is downloaded; the rest is fetched by a later pull). Returns the number of files downloaded."""
        with self.lock:
            for rec in self._records():
                meta = rec.meta or {}
                self.last_utc = max(self.last_utc, rec.written_utc)
                for rel in meta.get("deleted", []):
                    self.files.pop(rel, None)
                    self.refs.pop(rel, None)
                    self._pending.pop(rel, None)
                    if rel in self.known:
                        (self.root / rel).unlink(missing_ok=True)
                        self.known.pop(rel, None)
                for rel, ref in rec.files.items():
                    self.files[rel] = (ref.size, int(meta["mtime_ns"][rel]))
                    self.refs[rel] = ref
                    self._pending[rel] = ref.key
            n = 0
            for rel in sorted(self._pending):
                if only is not None and not only(rel):
                    continue
                n += self._fetch(rel, self._pending.pop(rel))
            self.stats["pulled_files"] += n
            return n

    def _fetch(self, rel: str, key: str) -> int:
        size, mtime_ns = self.files[rel]
        local = self.root / rel
        try:
            st = local.stat()
            if (st.st_size, st.st_mtime_ns) == (size, mtime_ns):
                self.known[rel] = (size, mtime_ns)
                return 0
        except OSError:
            pass
        try:
            self.store.get_file(key, local)
        except FileNotFoundError:
            raise InputError(f"{self.store.describe()}: {key}", f"recorded object of {rel} is missing") from None
        os.utime(local, ns=(mtime_ns, mtime_ns))
        self.known[rel] = (size, mtime_ns)
        return 1

    # ------------------------------------------------------------------ push
    def _scan(self) -> dict[str, tuple[int, int]]:
        out = {}
        for dirpath, dirnames, filenames in os.walk(self.root):
            rel_dir = os.path.relpath(dirpath, self.root)
            if rel_dir == ".":
                dirnames[:] = [d for d in dirnames if d not in _SKIP_DIRS]
            dirnames[:] = [d for d in dirnames if not d.startswith(".")]
            for name in filenames:
                if name.startswith("."):
                    continue  # a file being written (storage.atomic) or a lock file
                rel = name if rel_dir == "." else f"{rel_dir}/{name}".replace(os.sep, "/")
                try:
                    st = os.stat(os.path.join(dirpath, name))
                except OSError:
                    continue
                out[rel] = (st.st_size, st.st_mtime_ns)
        return out

    def changes(self) -> tuple[dict[str, tuple[int, int]], list[str]]:
        """(changed or new files {rel: (size, mtime_ns)}, deleted files) since the last pull / push."""
        now = self._scan()
        changed = {r: s for r, s in now.items() if self.known.get(r) != s and self.files.get(r) != s}
        deleted = sorted(r for r in self.known if r not in now and r not in self._pending)
        return changed, deleted

    def push(self, label: str = "") -> UnitRecord | None:
        """Publish this process's changes as one commit (None when there are none)."""
        with self.lock:
            changed, deleted = self.changes()
            if not changed and not deleted:
                return None
            seq = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}"
            meta = {"mtime_ns": {r: s[1] for r, s in changed.items()}, "deleted": deleted, "label": label}
            rec = put_unit_outputs(self.store, SYNC_STAGE, seq, {r: self.root / r for r in sorted(changed)}, meta)
            self.seen.add(f"{RECORDS}/{SYNC_STAGE}/{seq}.json")
            for r, s in changed.items():
                self.known[r] = self.files[r] = s
                self.refs[r] = rec.files[r]
                self._pending.pop(r, None)  # an older recorded version not fetched yet is superseded
            for r in deleted:
                self.known.pop(r, None)
                self.files.pop(r, None)
                self.refs.pop(r, None)
            self.last_utc = max(self.last_utc, rec.written_utc)
            self.stats["pushed_files"] += len(changed)
            self.stats["commits"] += 1
            return rec


    def compact(self) -> int:
        """Fold every commit this mirror has pulled into one record naming each live file's current object,
        then delete the folded records: superseded objects become unrecorded, for the sweep. Call with
        the run lease held, after :meth:`pull`. Returns the number of records folded away."""
        with self.lock:
            old = sorted(self.seen)
            if len(old) < 2:
                return 0
            seq = f"{time.time_ns():020d}-{uuid.uuid4().hex[:8]}"
            meta = {"mtime_ns": {r: self.files[r][1] for r in self.refs}, "deleted": [], "label": "compacted"}
            # dated as the last commit it folds, so a commit it did not see (a task of a killed run still
            # finishing) sorts after it and is not undone
            rec = UnitRecord(SYNC_STAGE, seq, "compacted", dict(self.refs), self.last_utc, meta)
            key = f"{RECORDS}/{SYNC_STAGE}/{seq}.json"
            self.store.put(key, json.dumps(rec.to_json(), sort_keys=True).encode())  # the new state first
            self.seen.add(key)
            self.store.delete(old)
            self.seen.difference_update(old)
            return len(old)


_MIRRORS: dict[tuple[str, str], Mirror] = {}
_MIRRORS_LOCK = threading.Lock()


def mirror_root(url: str, cache: str | Path) -> Path:
    """This process's mirror folder of the work dir ``url`` under the cache folder ``cache``."""
    return Path(cache) / "work" / f"{hashlib.sha256(url.encode()).hexdigest()[:12]}-{os.getpid()}"


def mirror_of(store: Store, cache: str | Path) -> Mirror:
    """The process-wide :class:`Mirror` of ``store`` (one per work dir URL and process)."""
    root = mirror_root(store.url, cache)
    with _MIRRORS_LOCK:
        m = _MIRRORS.get((store.url, str(root)))
        if m is None:
            m = _MIRRORS[(store.url, str(root))] = Mirror(store, root)
    return m


__all__ = ["SYNC_STAGE", "Mirror", "mirror_of", "mirror_root"]
