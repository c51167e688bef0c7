"""One interface over a local folder and an object store (``s3://bucket/prefix``): the layer a work dir
and its inputs stand on when workers share no disk.

A :class:`Store` names objects by ``/``-separated keys relative to its root. Locally every write goes to
a temporary name and is renamed into place (POSIX, as :mod:`storage.atomic`); on S3 a single PUT is
atomic, there is no rename, and a conditional PUT (``If-None-Match: *`` / ``If-Match: etag``) is the only
arbiter between writers (see :mod:`storage.objstore.commit` and :mod:`storage.objstore.lock`).

Where the endpoint and credentials come from, first match wins:

- an explicit ``storage:`` options dict (``endpoint_url``, ``region``, ``profile``, ``key``, ``secret``,
  ``token``, ``anon``);
- the standard environment: ``AWS_ENDPOINT_URL_S3`` / ``AWS_ENDPOINT_URL``, ``AWS_DEFAULT_REGION`` /
  ``AWS_REGION``, ``AWS_PROFILE``, and ``AWS_ACCESS_KEY_ID`` / ``AWS_SECRET_ACCESS_KEY`` /
  ``AWS_SESSION_TOKEN``, which botocore reads itself (so a :class:`Store` built from the environment holds
  no secret and pickles without one).

Credentials are never part of a message: :meth:`Store.describe` names a store by URL and endpoint only,
and every error raised here passes through :func:`redact`.

>>> s = open_store("file:///tmp/ms3d-doctest-store")
>>> s.is_local, s.describe()
(True, '/tmp/ms3d-doctest-store')
>>> redact("Credential=AKIDEXAMPLE/20260101/us-east-1/s3 X-Amz-Signature=abc123", ["AKIDEXAMPLE"])
'Credential=*** X-Amz-Signature=***'
"""

from __future__ import annotations

import hashlib
import os
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath

from storage.atomic import atomic_path, write_bytes_atomic
from storage.errors import InputError
from storage.objstore.cond import ConditionalOps, PreconditionFailed, backend_errors
from storage.objstore.env import (
    _SECRET_OPTIONS,
    install_log_redaction,
    redact,
    resolve_options,
)


@dataclass(frozen=True)
class ObjectInfo:
    """One stored object: key relative to the store root, size in bytes, modified time (epoch s, UTC)."""

    key: str
    size: int
    mtime: float


@dataclass
class StoreStats:
    """What a store has done: requests by operation (one per HTTP request on S3), bytes read/written."""

    requests: Counter = field(default_factory=Counter)
    bytes_read: int = 0
    bytes_written: int = 0
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def add(self, op: str | None = None, n: int = 1, read: int = 0, written: int = 0) -> None:
        """Count ``n`` requests of ``op`` and the bytes moved (safe from the threads of storage.objstore.pool)."""
        with self._lock:
            if op is not None:
                self.requests[op] += n
            self.bytes_read += read
            self.bytes_written += written

    @property
    def n_requests(self) -> int:
        return sum(self.requests.values())


def check_key(key: str) -> str:
    """``key`` if it is a clean relative key (no leading ``/``, no ``.``/``..``/empty parts), else ValueError."""
    parts = str(key).split("/")
    if not key or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"bad store key {key!r}: use a relative a/b/c key without '.', '..' or '//'")
    return str(key)


class Store(ConditionalOps):
    """A local folder or an object-store prefix, addressed by keys. Use :func:`open_store`.

    Errors from the backend are raised as InputError naming ``describe()/key`` (credentials redacted);
    a missing key raises FileNotFoundError (the caller decides whether that is an error).
    """

    def __init__(self, url: str, root: str, fs=None, options: dict | None = None):
        self.url, self.root, self._fs = url, root, fs
        self._options = dict(options or {})
        self._secrets = tuple(self._options[k] for k in _SECRET_OPTIONS if self._options.get(k))
        self.stats = StoreStats()

    @property
    def is_local(self) -> bool:
        return self._fs is None

    @property
    def fs(self):
        """The fsspec filesystem of a remote store (None for a local one)."""
        return self._fs

    def describe(self) -> str:
        """URL and endpoint, never credentials: safe for any log line or error."""
        ep = self._options.get("endpoint_url")
        return redact(self.url + (f" (endpoint {ep})" if ep else ""), self._secrets)

    def redact(self, text: str) -> str:
        return redact(text, self._secrets)

    def __repr__(self) -> str:
        return f"Store({self.describe()!r})"

    def __reduce__(self):  # to a Dask worker: the URL and options; credentials from the worker's env
        return (open_store, (self.url, self._options))

    def path(self, key: str) -> str:
        """The backend path of ``key`` (local file path, or ``bucket/prefix/key``)."""
        return f"{self.root.rstrip('/')}/{check_key(key)}"

    def _fail(self, key: str, what: str, exc: BaseException) -> InputError:
        return InputError(f"{self.describe()}: {key}", self.redact(f"cannot {what} ({type(exc).__name__}: {exc})"))

    def _count(self, op: str, n: int = 1) -> None:
        self.stats.add(op, n)

    def put(self, key: str, data: bytes) -> str | None:
        """Write ``data`` at ``key`` (atomically: rename locally, one PUT on S3). Returns the ETag (S3)."""
        self.stats.add(written=len(data))
        if self.is_local:
            write_bytes_atomic(self.path(key), data)
            return None
        return self._put_object(key, data)

    def put_file(self, key: str, local_path: str | Path) -> None:
        """Upload (or atomically copy) a local file to ``key``; large files go as one multipart upload,
        which S3 also publishes atomically on completion."""
        size = Path(local_path).stat().st_size
        self.stats.add(written=size)
        if self.is_local:
            import shutil

            with atomic_path(self.path(key)) as tmp:
                shutil.copyfile(local_path, tmp)
            return
        chunk = 50 << 20  # s3fs's multipart chunk: create + one per part + complete above 2 chunks
        self._count("PutObject" if size < 2 * chunk else "MultipartUpload", 1 if size < 2 * chunk else
                    2 + -(-size // chunk))
        try:
            self._fs.put_file(str(local_path), self.path(key))
        except backend_errors() as exc:
            raise self._fail(key, "upload", exc) from None

    def get_file(self, key: str, local_path: str | Path) -> Path:
        """Stage an object to a local file (written atomically): for readers that need a real path."""
        with atomic_path(local_path) as tmp:
            if self.is_local:
                import shutil

                shutil.copyfile(self.path(key), tmp)
            else:
                self._count("GetObject")
                try:
                    self._fs.get_file(self.path(key), str(tmp))
                except FileNotFoundError:
                    raise
                except backend_errors() as exc:
                    raise self._fail(key, "download", exc) from None
        self.stats.add(read=os.path.getsize(local_path))
        return Path(local_path)

    def get(self, key: str) -> bytes:
        """The whole object (FileNotFoundError when absent)."""
        return self.get_range(key, None, None)

    def get_range(self, key: str, start: int | None, end: int | None) -> bytes:
        """Bytes ``[start, end)`` of the object (None: from the start / to the end); one GET on S3."""
        if not self.is_local:
            if end is not None and end <= (start or 0):
                return b""
            return self._get_object(key, start, end)[0]
        with open(self.path(key), "rb") as f:
            f.seek(start or 0)
            data = f.read() if end is None else f.read(end - (start or 0))
        self.stats.add(read=len(data))
        return data

    def size(self, key: str) -> int:
        if self.is_local:
            return os.path.getsize(self.path(key))
        self._count("HeadObject")
        try:
            return int(self._fs.info(self.path(key))["size"])
        except FileNotFoundError:
            raise
        except backend_errors() as exc:
            raise self._fail(key, "stat", exc) from None

    def exists(self, key: str) -> bool:
        try:
            self.size(key)
            return True
        except FileNotFoundError:
            return False

    def list(self, prefix: str = "") -> list[ObjectInfo]:
        """Every object under ``prefix`` (a key folder, '' for all), sorted by key."""
        base = self.root.rstrip("/") + ("/" + check_key(prefix.strip("/")) if prefix.strip("/") else "")
        if self.is_local:
            d = Path(base)
            files = [p for p in d.rglob("*") if p.is_file()] if d.is_dir() else []
            out = [ObjectInfo(p.relative_to(self.root).as_posix(), (st := p.stat()).st_size, st.st_mtime)
                   for p in files]
            return sorted(out, key=lambda o: o.key)
        self._count("ListObjectsV2")
        try:
            found = self._fs.find(base, detail=True)
        except FileNotFoundError:
            return []
        except backend_errors() as exc:
            raise self._fail(prefix, "list", exc) from None
        n = len(self.root.rstrip("/")) + 1
        out = [ObjectInfo(p[n:], int(d["size"]), _mtime(d)) for p, d in found.items() if d.get("type") == "file"]
        self._count("ListObjectsV2", max(0, (len(out) - 1) // 1000))
        return sorted(out, key=lambda o: o.key)

    def delete(self, keys) -> int:
        """Delete ``keys`` (absent ones are ignored); returns how many were asked for."""
        keys = [check_key(k) for k in keys]
        if not keys:
            return 0
        if self.is_local:
            for k in keys:
                Path(self.path(k)).unlink(missing_ok=True)
            return len(keys)
        self._count("DeleteObjects", -(-len(keys) // 1000))
        try:
            self._fs.rm([self.path(k) for k in keys])
        except FileNotFoundError:
            pass
        except backend_errors() as exc:
            raise self._fail(keys[0], "delete", exc) from None
        return len(keys)

    # conditional operations: object stores only (a local work dir keeps its flock lock)
def _mtime(d: dict) -> float:
    lm = d.get("LastModified") or d.get("mtime")
    return lm.timestamp() if hasattr(lm, "timestamp") else float(lm or time.time())


def open_store(url: str | Path, options: dict | None = None) -> Store:
    """A :class:`Store` for a local path, ``file://`` URL or ``s3://bucket[/prefix]`` URL.

    options: the ``storage:`` options dict (OPTION_KEYS), over the environment. Raises InputError for an
    unsupported scheme or a bad option (one line, no credentials).
    """
    text = str(url)
    if "://" not in text or text.startswith("file://"):
        local = text.removeprefix("file://")
        root = str(Path(local).absolute())
        return Store(root, root)
    scheme, _, rest = text.partition("://")
    if scheme not in ("s3", "s3a"):
        raise InputError(redact(text), f"unsupported storage scheme {scheme!r}: use a local path, file:// or s3://")
    if "@" in rest.split("/", 1)[0]:
        raise InputError(redact(text), "credentials in the URL are not accepted: use the environment or "
                                       "the storage: options")
    bucket_prefix = str(PurePosixPath(rest.strip("/")))
    if not rest.strip("/"):
        raise InputError(text, "no bucket named (expected s3://bucket/prefix)")
    opts = resolve_options(options)
    install_log_redaction()
    import s3fs

    kwargs = {"skip_instance_cache": True, "use_listings_cache": False}
    if opts.get("endpoint_url"):
        kwargs["endpoint_url"] = opts["endpoint_url"]
    if opts.get("region"):
        kwargs["client_kwargs"] = {"region_name": opts["region"]}
    for k in ("profile", "key", "secret", "token", "anon"):
        if k in opts:
            kwargs[k] = opts[k]
    fs = s3fs.S3FileSystem(**kwargs)
    return Store(f"s3://{bucket_prefix}", bucket_prefix, fs, opts)


__all__ = ["ObjectInfo", "PreconditionFailed", "Store", "StoreStats", "check_key", "open_store",
           "redact", "resolve_options", "sha256_bytes"]


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()
