"""A node-local, content-addressed cache of immutable objects: ``{root}/{sha[:2]}/{sha}``.

Recorded objects never change (a rewrite gets a new key and a new digest), so a copy named by its sha256
is valid for as long as it exists, in any process and across restarts: a file appears under its digest only
by an atomic rename of a copy whose digest was checked. The cache is shared by the threads of a process
(one lock per digest while it is fetched) and by the processes of a node (renames never collide: the bytes
are the same). It is bounded: when it holds more than ``max_bytes`` the least recently used files (by
mtime, touched on every hit) are deleted until it holds ``low_water`` of the bound.

``MS3D_CACHE_MAX_GB`` sets the bound (default 20 GB).
"""

from __future__ import annotations

import os
import shutil
import threading
import uuid
from collections.abc import Callable
from pathlib import Path

from storage.objstore.commit import _sha256_file

DEFAULT_MAX_GB = 20.0
LOW_WATER = 0.8


def default_max_bytes() -> int:
    return int(float(os.environ.get("MS3D_CACHE_MAX_GB", DEFAULT_MAX_GB)) * 1e9)


class ContentCache:
    """Immutable objects by sha256 under ``root``, at most ``max_bytes`` (see the module docstring).

    ``stats``: hits, misses, bytes fetched (misses) and evicted files."""

    def __init__(self, root: str | Path, max_bytes: int | None = None):
        self.root = Path(root)
        self.max_bytes = default_max_bytes() if max_bytes is None else int(max_bytes)
        self._locks: dict[str, threading.Lock] = {}
        self._guard = threading.Lock()
        self._added = 0  # bytes inserted since the last size check
        self.stats = {"hits": 0, "misses": 0, "bytes_fetched": 0, "evicted": 0}

    def holds(self, sha256: str, size: int) -> bool:
        """Whether the object ``sha256`` of ``size`` bytes is in the cache now (a copy costs no request)."""
        return _valid(self.path_of(sha256), size)

    def path_of(self, sha256: str) -> Path:
        if len(sha256) != 64 or any(c not in "0123456789abcdef" for c in sha256):
            raise ValueError(f"not a sha256 hex digest: {sha256!r}")
        return self.root / sha256[:2] / sha256

    def _lock(self, sha256: str) -> threading.Lock:
        with self._guard:
            return self._locks.setdefault(sha256, threading.Lock())

    def materialise(self, sha256: str, size: int, fetch: Callable[[Path], None], dest: str | Path) -> bool:
        """Write the object ``sha256`` (``size`` bytes) to ``dest`` (atomically): from the cache, or by
        ``fetch(tmp_path)`` (download into a temporary file) when absent. Returns True on a cache hit.
        Raises ValueError when fetched bytes do not match the digest (nothing is cached then)."""
        dest, cached = Path(dest), self.path_of(sha256)
        with self._lock(sha256):
            for attempt in range(2):
                hit = _valid(cached, size)
                if hit:
                    os.utime(cached)  # most recently used
                else:
                    self._fetch_into(cached, sha256, size, fetch)
                try:
                    _copy_atomic(cached, dest)
                    break
                except FileNotFoundError:  # evicted by another process between the check and the copy
                    if attempt:
                        raise
            self.stats["hits" if hit else "misses"] += 1
        if self._added > self.max_bytes * (1 - LOW_WATER):
            self.evict()
        return hit

    def _fetch_into(self, cached: Path, sha256: str, size: int, fetch: Callable[[Path], None]) -> None:
        cached.parent.mkdir(parents=True, exist_ok=True)
        tmp = cached.parent / f".{sha256}.{uuid.uuid4().hex[:8]}.part"
        try:
            fetch(tmp)
            digest, n = _sha256_file(tmp)
            if digest != sha256 or n != size:
                raise ValueError(f"fetched object does not match its record (sha256/size {n} != {size})")
            os.replace(tmp, cached)
        finally:
            tmp.unlink(missing_ok=True)
        self.stats["bytes_fetched"] += size
        self._added += size

    def held_bytes(self) -> int:
        return sum(p.stat().st_size for p in self._files())

    def _files(self) -> list[Path]:
        if not self.root.is_dir():
            return []
        return [p for p in self.root.glob("??/*") if not p.name.startswith(".")]

    def evict(self) -> int:
        """Delete least recently used files until the cache holds <= LOW_WATER x max_bytes, if it holds more
        than max_bytes. Returns the number of files deleted."""
        with self._guard:
            self._added = 0
            files = []
            for p in self._files():
                try:
                    st = p.stat()
                except OSError:
                    continue
                files.append((st.st_mtime, st.st_size, p))
            total = sum(f[1] for f in files)
            if total <= self.max_bytes:
                return 0
            gone = 0
            for _, size, p in sorted(files):
                if total <= LOW_WATER * self.max_bytes:
                    break
                lk = self._locks.get(p.name)
                if lk is not None and lk.locked():
                    continue  # being materialised by a thread of this process
                p.unlink(missing_ok=True)  # a reader copying it keeps its open handle (POSIX)
                total -= size
                gone += 1
            self.stats["evicted"] += gone
            return gone


def _valid(path: Path, size: int) -> bool:
    try:
        return path.stat().st_size == size
    except OSError:
        return False




def _copy_atomic(src: Path, dest: Path) -> None:
    """A private copy (never a hard link: local code may rewrite its files in place)."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.parent / f".{dest.name}.{uuid.uuid4().hex[:8]}.tmp"
    try:
        shutil.copyfile(src, tmp)
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)


_CACHES: dict[str, ContentCache] = {}
_CACHES_LOCK = threading.Lock()


def content_cache(root: str | Path) -> ContentCache:
    """The process-wide cache at ``root`` (shared by its threads)."""
    key = str(Path(root).absolute())
    with _CACHES_LOCK:
        c = _CACHES.get(key)
        if c is None:
            c = _CACHES[key] = ContentCache(key)
    return c


def content_caches() -> list[ContentCache]:
    """Every content cache this process has opened."""
    with _CACHES_LOCK:
        return list(_CACHES.values())


__all__ = ["ContentCache", "content_cache", "content_caches", "default_max_bytes"]
