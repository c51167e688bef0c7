"""A work dir on an object store, used through a local mirror ("sync-through"): each process (the flow's
driver, each Dask worker) keeps its own copy of the recorded work dir, runs the ordinary local code on
it, and publishes what it changed as one commit of :mod:`storage.objstore.commit`.

::

    s3://bucket/prefix/
      records/sync/{seq}.json        one commit: logical file -> object key, size, sha256; meta: each file's
                                     mtime_ns and file_fingerprint, and the files it deleted
      objects/sync/{seq}/{token}/…   the objects of that commit (written before its record)
      .lock.json                     the run lease (storage.objstore.lock)

- **pull** (:meth:`Mirror.pull`): list the records, read the ones this process has not seen, fold them in
  order (a later commit of a file wins; a deletion removes it) and download each file whose local copy
  differs (of those a predicate names), setting its mtime to the producer's, so mtime-based fingerprints
  agree in every process. Only recorded objects are ever read: an object written by a unit that died before
  its record is invisible. A file the pull left out is still known by its record: a mirror answers
  :mod:`storage.recorded` for its folder (exists, size, mtime, sha256, fingerprint) and downloads it when code
  reads it (:meth:`Mirror.fetch`): the driver plans from the records this way (``flows.remote.driver_reads``).
- **push** (:meth:`Mirror.push`): every file of the mirror whose (size, mtime) differs from what this
  process last pulled or pushed, and every such file that is gone (or deleted with ``storage.recorded.unlink``
  before it was downloaded), as one commit (objects, then the record).
  A task's manifest records (``manifest.d/``) are files like any other, so a unit's outputs and its
  "done" record become visible together, or not at all.

Commits are **fenced by the run** (:mod:`storage.objstore.epoch`): a run takes an epoch with its lease, and
every commit of the run (the driver's and its tasks') is recorded under it as
``records/sync/{epoch:010d}-{lamport:012d}-{token}.json``. Readers fold only the records the rule of
:func:`storage.objstore.epoch.accepted` accepts (the latest epoch's, and the earlier ones its seal names), in
(epoch, Lamport counter) order, never by a writer's clock: a superseded run's late commit is ignored by every
reader, and its tasks learn before they commit that a later run has begun (:class:`RunSuperseded`). When a
mirror sees a later epoch than the state it holds, it reads that state afresh (a compaction may have
replaced the records it folded) and deletes its local copies of files the state no longer names: a
long-lived worker never acts on a file it did not read from the store for this run.

Each thread of each process has its own mirror folder (:mod:`storage.objstore.folders`: the URL's hash, the
process id, a token of this process instance and the thread), so a push publishes only what its own task wrote; folders
of processes that are gone are deleted when a process opens its first mirror of a URL. Downloads go through
the node's content-addressed cache of recorded objects (:mod:`storage.objstore.cas`, ``{cache}/objects``,
keyed by each object's recorded sha256, bounded by ``MS3D_CACHE_MAX_GB``): a thread, a restarted process or
a new driver on the same node copies an object it already holds instead of downloading it again.
"""

from __future__ import annotations

import json
import os
import threading
import uuid
from pathlib import Path

from storage import recorded
from storage.atomic import local_file_fingerprint
from storage.errors import InputError, Ms3dError
from storage.objstore.cas import content_cache
from storage.objstore.commit import RECORDS, UnitRecord, put_unit_outputs
from storage.objstore.download import download
from storage.objstore.epoch import accepted, is_current, latest_epoch, parse_record_unit, record_unit
from storage.objstore.folders import mirror_folder, sweep_stale_folders
from storage.objstore.pool import first_error, io_map
from storage.objstore.store import Store

SYNC_STAGE = "sync"
_SKIP_DIRS = ("prefect",)  # the driver's own Prefect database stays local
_INSTANCE = uuid.uuid4().hex[:8]  # this process instance (a restarted process may reuse the pid)


class RunSuperseded(Ms3dError):
    """A later run has begun on the work dir: this run's task stops without committing anything."""


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
        self._pending_sorted: list[str] | None = None  # sorted keys of _pending (None: to rebuild)
        self._forgotten: set[str] = set()  # recorded files deleted here before they were downloaded
        self.refs: dict = {}  # folded remote state: rel -> OutputRef of its current object
        self.fps: dict[str, str | None] = {}  # folded remote state: rel -> its file_fingerprint, when recorded
        self.last_utc = 0.0  # written_utc of the latest commit folded
        self.lock = threading.RLock()
        self.lease = None  # the run's Lease while the driver holds it (flows.remote.remote_run)
        self.epoch: int | None = None  # the run epoch this mirror commits under (None: unfenced, tests)
        self.state_epoch = 0  # the latest epoch the folded state was read under
        self.lamport = 0  # the largest commit counter seen or written
        self.cas = None  # a ContentCache of recorded objects shared by the node's mirrors (mirror_of sets it)
        # a mirror that downloads what it reads when it reads it (the driver: flows.remote.remote_run): a file it
        # wrote before it downloaded the recorded version is its newer version, never overwritten by a pull
        self.lazy = False
        self.stats = {"pulled_files": 0, "pushed_files": 0, "commits": 0, "records_read": 0, "cache_hits": 0}

    # ------------------------------------------------------------------ pull
    def record_keys(self) -> list[str]:
        """Every sync record key in the store (one LIST)."""
        return [i.key for i in self.store.list(f"{RECORDS}/{SYNC_STAGE}") if i.key.endswith(".json")]

    def check_current(self) -> None:
        """RunSuperseded when a later run than this mirror's epoch has begun (one HEAD); nothing unfenced."""
        if self.epoch is not None and not is_current(self.store, self.epoch):
            raise RunSuperseded(f"{self.store.describe()}: a later ms3d run has begun on this work dir; this run's "
                                "task stops without committing")

    def _reset(self) -> None:
        """Forget the folded state (its local files stay until :meth:`pull` finds them unnamed)."""
        self.files, self.refs, self.fps, self._pending, self.seen = {}, {}, {}, {}, set()
        self._forgotten, self._pending_sorted = set(), None

    def _records(self) -> list[UnitRecord]:
        latest = latest_epoch(self.store)
        n = latest.number if latest is not None else 0
        if n > self.state_epoch and self.seen:  # a later run's state: read it afresh
            self._reset()
        self.state_epoch = max(self.state_epoch, n)
        new = []
        for key in sorted(accepted(self.record_keys(), latest) - self.seen):
            try:
                d = json.loads(self.store.get(key))
                new.append(UnitRecord.from_json(d))
            except FileNotFoundError:
                continue
            except (ValueError, KeyError, TypeError) as exc:
                raise InputError(f"{self.store.describe()}: {key}", f"not a valid sync record ({exc})") from None
            self.seen.add(key)
        self.stats["records_read"] += len(new)
        order = sorted(new, key=lambda r: (*parse_record_unit(r.unit), r.unit))
        if order:
            self.lamport = max(self.lamport, max(parse_record_unit(r.unit)[1] for r in order))
        return order

    def pull(self, only=None) -> int:
        """Bring the mirror up to the recorded state (``only``: a predicate on relative paths limiting what
        is downloaded; the rest is fetched by a later pull). Returns the number of files downloaded."""
        with self.lock:
            for rec in self._records():
                meta = rec.meta or {}
                self.last_utc = max(self.last_utc, rec.written_utc)
                fps = meta.get("fingerprint") or {}
                for rel in meta.get("deleted", []):
                    self.files.pop(rel, None)
                    self.refs.pop(rel, None)
                    self.fps.pop(rel, None)
                    self._pending.pop(rel, None)
                    if rel in self.known:
                        (self.root / rel).unlink(missing_ok=True)
                        self.known.pop(rel, None)
                for rel, ref in rec.files.items():
                    self.files[rel] = (ref.size, int(meta["mtime_ns"][rel]))
                    self.refs[rel] = ref
                    self.fps[rel] = fps.get(rel)  # None: recorded before commits carried fingerprints
                    self._pending[rel] = ref.key
                    self._forgotten.discard(rel)  # written again by another process
            for rel in [r for r in self.known if r not in self.files]:  # gone from the state read afresh
                (self.root / rel).unlink(missing_ok=True)
                self.known.pop(rel, None)
            self._pending_sorted = None
            return self.fetch([rel for rel in sorted(self._pending) if only is None or only(rel)])

    def fetch(self, rels) -> int:
        """Download the recorded files ``rels`` that are not downloaded yet (no request for the records: what
        the last :meth:`pull` folded), :func:`storage.objstore.pool.io_threads` at a time. Returns the number
        of files downloaded. A file that fails stays pending (a later read tries again); the first failure
        is raised once every other file is in."""
        with self.lock:
            todo = []
            for rel in rels:
                key = self._pending.pop(rel, None)
                if key is not None:
                    self._pending_sorted = None
                    todo.append((rel, key, self.files[rel], self.refs.get(rel), rel in self.known))
            got = io_map(lambda job: download(self.store, self.cas, self.root, self.lazy, job), todo,
                         concurrent=not self.store.is_local)
            n = 0
            for (rel, key, *_), r in zip(todo, got):
                if isinstance(r, BaseException):
                    self._pending[rel] = key
                    self._pending_sorted = None
                    continue
                downloaded, hit, state = r
                if state is not None:
                    self.known[rel] = state
                n += downloaded
                self.stats["cache_hits"] += hit
            self.stats["pulled_files"] += n
            if (err := first_error(got)) is not None:
                raise err
            return n

    # ------------------------------------------------------------------ what the records say (storage.recorded)
    def recorded_state(self, rel: str):
        """(the recorded :class:`storage.recorded.FileState` of ``rel`` or None, whether it is not downloaded)."""
        from storage.recorded import FileState

        with self.lock:
            got = self.files.get(rel)
            if got is None:
                return None, False
            ref = self.refs.get(rel)
            return FileState(got[0], got[1], ref.sha256 if ref is not None else None, self.fps.get(rel)), \
                rel in self._pending

    def pending_under(self, rel_dir: str) -> list[str]:
        """The recorded files under the folder ``rel_dir`` ('' for all) not downloaded yet."""
        import bisect

        with self.lock:
            if self._pending_sorted is None:
                self._pending_sorted = sorted(self._pending)
            keys, prefix = self._pending_sorted, rel_dir.strip("/") + "/" if rel_dir.strip("/") not in ("", ".") else ""
            i = j = bisect.bisect_left(keys, prefix)
            while j < len(keys) and keys[j].startswith(prefix):
                j += 1
            return keys[i:j]

    def object_of(self, rel: str):
        """(store, object key, size) of the recorded file ``rel`` while it is not downloaded here nor held by the
        node's cache, else None: for readers that fetch byte ranges of it (:mod:`storage.patches.remote_read`)."""
        with self.lock:
            key, size, ref = self._pending.get(rel), self.files.get(rel, (0,))[0], self.refs.get(rel)
            cached = self.cas is not None and ref is not None and ref.sha256 and self.cas.holds(ref.sha256, size)
            return None if key is None or cached else (self.store, key, size)

    def forget(self, rels) -> None:
        """The recorded files ``rels`` were deleted here before they were downloaded: the next push publishes
        their deletion."""
        with self.lock:
            for rel in rels:
                if self._pending.pop(rel, None) is not None:
                    self._pending_sorted = None
                    self.files.pop(rel, None)
                    self.refs.pop(rel, None)
                    self.fps.pop(rel, None)
                    self._forgotten.add(rel)

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
        deleted = sorted({r for r in self.known if r not in now and r not in self._pending}
                         | {r for r in self._forgotten if r not in now})
        return changed, deleted

    def push(self, label: str = "") -> UnitRecord | None:
        """Publish this mirror's changes as one commit under its run epoch (None when there are none).
        Raises RunSuperseded, committing nothing, when a later run has begun."""
        with self.lock:
            changed, deleted = self.changes()
            if not changed and not deleted:
                return None
            self.check_current()
            self.lamport += 1
            seq = record_unit(self.epoch or 0, self.lamport, uuid.uuid4().hex[:8])
            fps = {r: local_file_fingerprint(self.root / r) for r in sorted(changed)}
            meta = {"mtime_ns": {r: s[1] for r, s in changed.items()}, "deleted": deleted, "label": label,
                    "epoch": self.epoch, "fingerprint": fps}
            rec = put_unit_outputs(self.store, SYNC_STAGE, seq, {r: self.root / r for r in sorted(changed)}, meta)
            self.seen.add(f"{RECORDS}/{SYNC_STAGE}/{seq}.json")
            for r, s in changed.items():
                self.known[r] = self.files[r] = s
                self.refs[r] = rec.files[r]
                self.fps[r] = fps[r]
                self._pending.pop(r, None)  # an older recorded version not fetched yet is superseded
                self._forgotten.discard(r)
            for r in deleted:
                self.known.pop(r, None)
                self.files.pop(r, None)
                self.refs.pop(r, None)
                self.fps.pop(r, None)
                self._pending.pop(r, None)
                self._forgotten.discard(r)
            self._pending_sorted = None
            self.last_utc = max(self.last_utc, rec.written_utc)
            self.stats["pushed_files"] += len(changed)
            self.stats["commits"] += 1
            return rec


    def release(self, keep=None) -> int:
        """Delete the local copies of the recorded files that are unchanged here (but those the predicate
        ``keep`` names); they stay known by their records (:mod:`storage.recorded`) and come back on a later
        pull or read, from the node's content cache when it holds them. A worker then keeps on scratch one copy
        of what it read (the cache's), not a mirror of the work dir. Returns how many files were released."""
        with self.lock:
            n = 0
            for rel, s in list(self.known.items()):
                if keep is not None and keep(rel):
                    continue
                try:
                    st = (self.root / rel).stat()
                except OSError:
                    continue
                if rel in self.refs and self.files.get(rel) == s == (st.st_size, st.st_mtime_ns):
                    (self.root / rel).unlink()
                    self.known.pop(rel)
                    self._pending[rel] = self.refs[rel].key
                    n += 1
            self._pending_sorted = None
            return n

    def compact(self) -> int:
        """Fold every commit this mirror has pulled into one record of its epoch naming each live file's
        current object (Lamport counter 0: before every commit of the run), then delete the folded records
        and every record no reader accepts (a superseded run's late commits): their objects become
        unrecorded, for the sweep. Call with the run lease held, right after the run's epoch began and
        :meth:`pull`. Returns the number of records deleted."""
        with self.lock:
            old = sorted(set(self.record_keys()) | self.seen)
            if len(old) < 2 and set(old) <= self.seen:
                return 0
            self.check_current()
            seq = record_unit(self.epoch or 0, 0, f"compacted{uuid.uuid4().hex[:8]}")
            meta = {"mtime_ns": {r: self.files[r][1] for r in self.refs}, "deleted": [], "label": "compacted",
                    "epoch": self.epoch, "fingerprint": {r: self.fps[r] for r in self.refs if self.fps.get(r)}}
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
    """This thread's mirror folder of the work dir ``url`` under the cache folder ``cache``."""
    return mirror_folder(url, cache, _INSTANCE)


def sweep_stale_mirrors(url: str, cache: str | Path) -> int:
    """Delete the mirror folders of ``url`` under ``cache`` of process instances that are gone; how many."""
    return sweep_stale_folders(url, cache, _INSTANCE)


_SWEPT: set[tuple[str, str]] = set()


def process_instance() -> str:
    """This process instance's token (a restarted process may reuse the pid, never the token)."""
    return _INSTANCE


def live_mirrors() -> list[Mirror]:
    """Every mirror this process has opened (one per work dir URL and thread)."""
    with _MIRRORS_LOCK:
        return list(_MIRRORS.values())


def mirror_of(store: Store, cache: str | Path) -> Mirror:
    """This thread's :class:`Mirror` of ``store`` (one per work dir URL, process instance and thread; a new one
    starts empty). The first in a process sweeps the folders of process instances that are gone."""
    root = mirror_root(store.url, cache)
    with _MIRRORS_LOCK:
        if (store.url, str(cache)) not in _SWEPT:
            _SWEPT.add((store.url, str(cache)))
            sweep_stale_mirrors(store.url, cache)
        m = _MIRRORS.get((store.url, str(root)))
        if m is None:
            import shutil

            shutil.rmtree(root, ignore_errors=True)  # never a leftover of another instance
            m = _MIRRORS[(store.url, str(root))] = Mirror(store, root)
            m.cas = content_cache(Path(cache) / "objects")
            recorded.register(m)  # what the records say about the files it has not downloaded
    return m


__all__ = ["SYNC_STAGE", "Mirror", "RunSuperseded", "live_mirrors", "mirror_of", "mirror_root", "process_instance",
           "sweep_stale_mirrors"]
