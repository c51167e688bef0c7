"""Inputs named by URL (``s3://bucket/key``): identity, fingerprints, discovery and staging to a local cache.

A URL stays the input's identity everywhere (its source id, its record in campus.json, the ingest units):
only the code that opens a file asks for a local copy, with :func:`local_input`. The copy lives in this
process's cache (``$MS3D_CACHE/inputs``, default ``./.ms3d-cache/inputs`` under the worker's cwd), at a
path that mirrors the object's key, so the files beside a mesh (its ``.mtl``, texture images, a
production's ``metadata.xml``) keep their relative layout. A copy is current when its size and
modification time equal the object's (the copy's mtime is set to the object's LastModified), so a
re-uploaded object is fetched again, and the copies on two workers fingerprint alike.

- :func:`url_fingerprint`: the object's ETag and size (one HEAD; nothing downloaded);
- :func:`discover_url`: a file URL, or a folder (key prefix) listed with the supported extensions;
- :func:`local_input`: a local path for a file or a folder URL (downloaded once per content);
- :func:`input_exists`: a file or folder exists, local path or URL.

Local paths pass through every function unchanged (one string test). A URL that cannot be read raises
InputError naming the URL (credentials redacted), one line.

>>> split_url("s3://bucket/campus/mls/a.laz")
('s3://bucket', 'campus/mls/a.laz')
"""

from __future__ import annotations

import hashlib
import os
import threading
from dataclasses import dataclass, replace
from pathlib import Path

from storage.errors import InputError
from storage.formats.production import Production, production_root_of, read_metadata
from storage.inputs.location import Location, is_url, split_embedded
from storage.objstore.store import Store, open_store, redact

CACHE_ENV = "MS3D_CACHE"
_STORES: dict[str, Store] = {}
_LOCK = threading.Lock()


def split_url(url: str) -> tuple[str, str]:
    """(bucket URL, key) of an object URL; InputError when no bucket or key is named."""
    scheme, _, rest = url.partition("://")
    bucket, _, key = rest.strip("/").partition("/")
    if not bucket or not key:
        raise InputError(redact(url), "expected s3://bucket/key")
    return f"{scheme}://{bucket}", key.rstrip("/")


def bucket_store(url: str) -> tuple[Store, str]:
    """(the process's Store of the URL's bucket, key): one store per bucket per process."""
    base, key = split_url(url)
    with _LOCK:
        store = _STORES.get(base)
        if store is None:
            store = _STORES[base] = open_store(base)
    return store, key


def input_stores() -> list[Store]:
    """Every input bucket's Store this process has opened (their ``stats``: what staging inputs cost)."""
    with _LOCK:
        return list(_STORES.values())


def cache_root() -> Path:
    """This process's input cache: ``$MS3D_CACHE/inputs`` or ``./.ms3d-cache/inputs``."""
    return Path(os.environ.get(CACHE_ENV) or Path.cwd() / ".ms3d-cache").absolute() / "inputs"


@dataclass(frozen=True)
class ObjectHead:
    """An object's size (bytes), ETag (quotes stripped; "" when unknown) and LastModified (epoch s)."""

    size: int
    etag: str
    mtime: float


def head(url: str) -> ObjectHead | None:
    """The object's :class:`ObjectHead` (one HEAD), or None when no object has this key."""
    store, key = bucket_store(url)
    store._count("HeadObject")
    try:
        info = store.fs.info(store.path(key))
    except FileNotFoundError:
        return None
    except Exception as exc:  # noqa: BLE001 - any backend failure becomes one line naming the URL
        raise InputError(redact(url), store.redact(f"cannot stat ({type(exc).__name__}: {exc})")) from None
    if info.get("type") != "file":
        return None
    lm = info.get("LastModified") or info.get("mtime")
    mtime = lm.timestamp() if hasattr(lm, "timestamp") else float(lm or 0.0)
    return ObjectHead(int(info["size"]), str(info.get("ETag") or "").strip('"'), mtime)


def url_fingerprint(url: str) -> str:
    """Content fingerprint of an object input: its ETag and size (InputError when it does not exist)."""
    h = head(url)
    if h is None:
        raise InputError(redact(url), "input does not exist (no object at this key)")
    return hashlib.sha256(f"s3:{h.etag}:{h.size}".encode()).hexdigest()[:32]


def list_url(url: str) -> list[tuple[str, int, float]]:
    """Every object under the folder URL ``url`` as (url, size, mtime), sorted by key."""
    store, key = bucket_store(url)
    base = split_url(url)[0]
    return [(f"{base}/{o.key}", o.size, o.mtime) for o in store.list(key)]


def discover_url(entry: str, kind: str, suffixes: frozenset[str], skipped: list) -> list[str]:
    """The input files of one config entry that is a URL: the object itself, or the objects under the
    folder (prefix) with a supported extension (hidden files and, for meshes, materials, textures and
    metadata left out silently, as :func:`storage.inputs.identity.discover` does locally; anything else appended
    to ``skipped`` with why). InputError when nothing is there."""
    if head(entry) is not None:
        return [entry]
    prefix = entry.rstrip("/")
    found = []
    for url, _, _ in list_url(prefix):
        rel = url[len(prefix) + 1:]
        suffix = Path(rel).suffix.lower()
        if any(part.startswith(".") for part in rel.split("/")):
            skipped.append((url, "hidden or temporary file"))
        elif suffix in suffixes:
            found.append(url)
        elif kind == "mesh" and suffix in {".mtl", ".jpg", ".jpeg", ".png", ".xml", ".tif", ".tiff"}:
            continue
        else:
            skipped.append((url, f"not a {kind} file (extension {suffix or 'none'!r})"))
    if not found and not list_url(prefix):
        raise InputError(redact(entry), f"{kind} input does not exist (no object or folder at this URL)")
    if not found:
        raise InputError(redact(entry), f"no {kind} files ({', '.join(sorted(suffixes))}) in this folder")
    return found


def mirror_path(url: str) -> Path:
    """Where the cache keeps the object ``url``: ``cache_root()/<bucket URL hash>/<key>``."""
    base, key = split_url(url)
    return cache_root() / hashlib.sha256(base.encode()).hexdigest()[:12] / key


def _current(local: Path, size: int, mtime: float) -> bool:
    try:
        st = local.stat()
    except OSError:
        return False
    return st.st_size == size and abs(st.st_mtime - mtime) < 1e-3


def _stage(url: str, size: int, mtime: float) -> Path:
    local = mirror_path(url)
    if _current(local, size, mtime):
        return local
    store, key = bucket_store(url)
    try:
        store.get_file(key, local)
    except FileNotFoundError:
        raise InputError(redact(url), "input does not exist (no object at this key)") from None
    except OSError as exc:
        raise InputError(redact(url), f"cannot stage to {local.parent} ({exc.strerror or exc})") from None
    os.utime(local, (mtime, mtime))
    return local


def stage_folder(url: str) -> Path | None:
    """Stage every object under the folder URL; its local mirror folder, or None when it is empty."""
    objects = list_url(url.rstrip("/"))
    for u, size, mtime in objects:
        _stage(u, size, mtime)
    return mirror_path(url.rstrip("/")) if objects else None


def local_input(path, siblings: bool = False) -> str:
    """A local path to read the input ``path`` from: ``path`` itself unless it is a URL; a URL of an
    object is downloaded into the cache (once per content), a folder URL staged whole.

    siblings: also stage the other objects of the file's folder (an OBJ's ``.mtl`` and textures) and,
    for a tile of a ContextCapture production, the production's ``metadata.xml``. InputError naming the
    URL when it cannot be staged."""
    if not is_url(path):
        return path
    h = head(path)
    if h is None:
        folder = stage_folder(path)
        if folder is None:
            raise InputError(redact(path), "input does not exist (no object or folder at this URL)")
        return str(folder)
    local = _stage(path, h.size, h.mtime)
    if siblings:
        parent = path.rsplit("/", 1)[0]
        for u, size, mtime in list_url(parent):
            if "/" not in u[len(parent) + 1:]:
                _stage(u, size, mtime)
        root = remote_production_root(path)
        if root is not None and (meta := head(f"{root}/metadata.xml")) is not None:
            _stage(f"{root}/metadata.xml", meta.size, meta.mtime)
    return str(local)


def staged_ref(local: str, url: str) -> str:
    """What a store records for a file read beside the input ``url`` (an OBJ's texture image): the URL of
    the object ``local`` was staged from, when ``url`` is a URL and ``local`` lies in the staged copy of
    its folder, so another process (another cache) stages it again; else ``local`` unchanged.

    >>> staged_ref("/data/mesh/t.jpg", "/data/mesh/a.obj")
    '/data/mesh/t.jpg'
    """
    if not is_url(url):
        return local
    parent = url.rsplit("/", 1)[0]
    try:
        rel = Path(local).resolve().relative_to(mirror_path(parent).resolve())
    except ValueError:
        return local
    return f"{parent}/{rel.as_posix()}"


def readable(ref) -> str:
    """A local path to open a recorded file reference: a URL is staged into this process's cache (once per
    content), a path is returned as it is (an embedded image: :func:`storage.formats.embedded.resolve_ref`)."""
    return local_input(ref) if is_url(ref) else ref


def input_exists(path) -> bool:
    """Whether an input file or folder exists (a local path, or an object / non-empty prefix); for an
    embedded image (``<file.glb>#image0``), whether its container does."""
    if (emb := split_embedded(path)) is not None and not is_url(path):
        return Path(emb[0]).exists()
    if not is_url(path):
        return Path(path).exists()
    return head(path) is not None or bool(list_url(path.rstrip("/")))


def input_is_file(path) -> bool:
    """Whether ``path`` is a file (a local file, or an object)."""
    return Path(path).is_file() if not is_url(path) else head(path) is not None


def remote_production_root(mesh_url: str) -> str | None:
    """The URL of the ContextCapture production a mesh URL belongs to (the one rule,
    :func:`storage.formats.production.production_root_of`, asked of the bucket), or None for an ordinary file."""
    root = production_root_of(Location(mesh_url), lambda loc: head(str(loc)) is not None)
    return None if root is None else str(root)


def remote_production_of(mesh_url: str):
    """The :class:`storage.formats.production.Production` of a mesh URL (its ``metadata.xml`` staged and read;
    root, metadata path and key are URLs / from the URL, the same on every worker), or None."""
    root = remote_production_root(mesh_url)
    if root is None:
        return None
    meta_url, meta = f"{root}/metadata.xml", None
    h = head(meta_url)
    if h is not None:
        try:
            meta = replace(read_metadata(_stage(meta_url, h.size, h.mtime)), path=meta_url)
        except InputError as e:
            raise InputError(redact(meta_url), e.problem) from None
    return Production(root, meta, int.from_bytes(hashlib.sha256(root.encode()).digest()[:8], "big"))


__all__ = [
    "ObjectHead",
    "bucket_store",
    "cache_root",
    "discover_url",
    "head",
    "input_exists",
    "input_is_file",
    "input_stores",
    "is_url",
    "list_url",
    "local_input",
    "mirror_path",
    "readable",
    "remote_production_of",
    "remote_production_root",
    "split_url",
    "stage_folder",
    "staged_ref",
    "url_fingerprint",
]
