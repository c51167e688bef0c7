"""Files a work dir's records name but this process has not downloaded: their state, and their bytes on demand.

A work dir on a bucket is used through a local mirror (:mod:`storage.objstore.mirror`) that folds the records of
every commit: for each file its size, its producer's mtime_ns, its sha256 and its cheap fingerprint
(:func:`storage.atomic.file_fingerprint`), without downloading it. A process that only plans (the flow's
driver) downloads little: the code that decides from a file's state (does it exist, its size and mtime, its
digest) asks here, and gets the local file's state when there is one, else what the records say. Code that
reads a file's bytes calls :func:`ensure_local` first (the tile stores, merged tiles and LOD meshes do it where
they are opened). A local work dir has no records: every function is then the plain local call, at the cost of
one dict lookup.

A mirror registers its folder (:func:`register`); the rules, per path under it:

- a local file is what it is (the recorded digests come with it while its size and mtime are the recorded
  ones: it is the recorded file);
- a file the records name and this process has not downloaded exists with the recorded state;
- a file this process downloaded and then deleted is gone (its deletion is published by the next push), and
  so is one deleted with :func:`unlink` before it was downloaded.

>>> state("/nonexistent/ms3d-doctest/a.json") is None
True
"""

from __future__ import annotations

import fnmatch
import os
import threading
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Protocol


@dataclass(frozen=True)
class FileState:
    """A file's size (bytes) and mtime_ns; its sha256 and cheap fingerprint when the records know them."""

    size: int
    mtime_ns: int
    sha256: str | None = None
    fingerprint: str | None = None


class RecordedFiles(Protocol):
    """What a mirror answers for the paths under its folder ``root`` (``rel``: a ``/``-separated path)."""

    root: Path

    def recorded_state(self, rel: str) -> tuple[FileState | None, bool]:
        """(the file's recorded state or None, whether it is recorded and not downloaded here)."""

    def pending_under(self, rel_dir: str) -> list[str]:
        """The recorded files under ``rel_dir`` ('' for all) that are not downloaded here."""

    def fetch(self, rels: list[str]) -> int:
        """Download these recorded files (those not downloaded yet); returns how many."""

    def forget(self, rels: list[str]) -> None:
        """These recorded files were deleted here: the next push publishes their deletion."""


_VIEWS: dict[Path, RecordedFiles] = {}
_LOCK = threading.Lock()


def register(view: RecordedFiles) -> None:
    """Answer for the paths under ``view.root`` from now on (until :func:`unregister`)."""
    with _LOCK:
        _VIEWS[Path(view.root).absolute()] = view


def unregister(root: str | Path) -> None:
    with _LOCK:
        _VIEWS.pop(Path(root).absolute(), None)


def owner(path: str | Path) -> tuple[RecordedFiles, str] | None:
    """(the view whose folder holds ``path``, its relative path) or None (a plain local path)."""
    if not _VIEWS:
        return None
    p = Path(path).absolute()
    for parent in (p, *p.parents):
        view = _VIEWS.get(parent)
        if view is not None:
            return view, p.relative_to(parent).as_posix()
    return None


def _local(path: str | Path) -> os.stat_result | None:
    try:
        return os.stat(path)
    except (FileNotFoundError, NotADirectoryError):
        return None


def state(path: str | Path) -> FileState | None:
    """The state of the file ``path`` (the module docstring's rules); None when there is none."""
    st = _local(path)
    own = owner(path)
    if own is None:
        return None if st is None or not _is_file(st) else FileState(st.st_size, st.st_mtime_ns)
    rec, pending = own[0].recorded_state(own[1])
    if st is not None:
        if not _is_file(st):
            return None
        if rec is not None and (rec.size, rec.mtime_ns) == (st.st_size, st.st_mtime_ns):
            return rec
        return FileState(st.st_size, st.st_mtime_ns)
    return rec if pending else None


def _is_file(st: os.stat_result) -> bool:
    import stat as stat_module

    return stat_module.S_ISREG(st.st_mode)


def is_file(path: str | Path) -> bool:
    return state(path) is not None


def is_dir(path: str | Path) -> bool:
    """A local folder, or one that holds recorded files not downloaded here."""
    if os.path.isdir(path):
        return True
    own = owner(path)
    return own is not None and bool(own[0].pending_under(own[1]))


def exists(path: str | Path) -> bool:
    return is_file(path) or is_dir(path)


def children(folder: str | Path) -> list[Path]:
    """The entries of ``folder`` (files and folders, local and recorded), sorted; [] when it is none."""
    folder = Path(folder)
    names = set()
    try:
        names.update(os.listdir(folder))
    except (FileNotFoundError, NotADirectoryError):
        pass
    own = owner(folder)
    if own is not None:
        view, rel = own
        n = len(rel) + 1 if rel not in ("", ".") else 0
        names.update(r[n:].split("/", 1)[0] for r in view.pending_under(rel if n else ""))
    return [folder / name for name in sorted(names)]


def glob(folder: str | Path, pattern: str) -> list[Path]:
    """The files and folders under ``folder`` matching ``pattern`` (``Path.glob`` with ``*`` / ``?`` parts and
    ``**`` for any depth), local and recorded, sorted."""
    folder = Path(folder)
    own = owner(folder)
    if own is None:
        return sorted(folder.glob(pattern))
    found = set(folder.glob(pattern))
    view, rel = own
    n = len(rel) + 1 if rel not in ("", ".") else 0
    parts = PurePosixPath(pattern).parts
    for r in view.pending_under(rel if n else ""):
        sub = PurePosixPath(r[n:]).parts
        for k in range(1, len(sub) + 1):  # the file itself or one of its folders may match
            if _match(sub[:k], parts):
                found.add(folder.joinpath(*sub[:k]))
    return sorted(p for p in found if os.path.isdir(p) or state(p) is not None)


def _match(parts: tuple[str, ...], pattern: tuple[str, ...]) -> bool:
    if not pattern:
        return not parts
    if pattern[0] == "**":
        return any(_match(parts[i:], pattern[1:]) for i in range(len(parts) + 1))
    return bool(parts) and fnmatch.fnmatchcase(parts[0], pattern[0]) and _match(parts[1:], pattern[1:])


def ensure_local(*paths: str | Path) -> int:
    """Download the recorded files ``paths`` name (a file, or every file under a folder) that this process has
    not downloaded yet, so that code may open them. Returns how many were downloaded."""
    wanted: dict[int, tuple[RecordedFiles, list[str]]] = {}
    for p in paths:
        own = owner(p)
        if own is None:
            continue
        view, rel = own
        rels = [rel] if view.recorded_state(rel)[1] else view.pending_under(rel)
        if rels:
            wanted.setdefault(id(view), (view, []))[1].extend(rels)
    return sum(view.fetch(rels) for view, rels in wanted.values())


def remote_object(path: str | Path) -> tuple | None:
    """(Store, object key, size in bytes) of the recorded file ``path`` while it is not downloaded here, for a
    reader that fetches byte ranges of it; None for a local file (or one already downloaded)."""
    own = owner(path)
    if own is None:
        return None
    view, rel = own
    object_of = getattr(view, "object_of", None)
    return None if object_of is None else object_of(rel)


def unlink(path: str | Path) -> None:
    """Delete the file ``path``, here and (by the next push of a mirror) in the records; no error when absent."""
    Path(path).unlink(missing_ok=True)
    own = owner(path)
    if own is not None and own[0].recorded_state(own[1])[1]:
        own[0].forget([own[1]])


def remove_tree(folder: str | Path) -> None:
    """Delete the folder ``folder`` and everything under it, here and in the records."""
    import shutil

    shutil.rmtree(folder, ignore_errors=True)
    own = owner(folder)
    if own is not None:
        pending = own[0].pending_under(own[1])
        if pending:
            own[0].forget(pending)


def recorded_digest(path: str | Path, kind: str) -> str | None:
    """The records' ``kind`` ("sha256" or "fingerprint") of the file ``path`` when they know it and the file is
    the recorded one (not downloaded, or downloaded and unchanged); else None (compute it from the bytes)."""
    if not _VIEWS:
        return None
    st = state(path)
    return None if st is None else getattr(st, kind)


__all__ = ["FileState", "RecordedFiles", "children", "ensure_local", "exists", "glob", "is_dir", "is_file", "owner",
           "recorded_digest", "register", "remove_tree", "state", "unlink", "unregister"]
