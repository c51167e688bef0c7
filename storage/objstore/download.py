"""One recorded file of a mirror downloaded (:meth:`storage.objstore.mirror.Mirror.fetch` runs several at once,
:mod:`storage.objstore.pool`): through the node's content-addressed cache when the record names the object's
sha256, its mtime set to the producer's so that mtime-based fingerprints agree in every process."""

from __future__ import annotations

import os
from pathlib import Path

from storage.errors import InputError


def download(store, cas, root: Path, lazy: bool, job: tuple) -> tuple[int, bool, tuple[int, int] | None]:
    """Download one file of a mirror (run in an I/O thread: reads the mirror's state, changes none of it).

    store: the work dir's Store; cas: the node's ContentCache or None; root: the mirror folder; lazy: whether
    the mirror downloads on read (a file it wrote before downloading the recorded version is newer: kept).
    job: (rel, object key, recorded (size, mtime_ns), its OutputRef or None, whether the mirror knew the file).
    Returns (1 if downloaded else 0, whether the cache served it, the file's new known state or None).
    """
    rel, key, (size, mtime_ns), ref, was_known = job
    local = root / rel
    try:
        st = local.stat()
        if (st.st_size, st.st_mtime_ns) == (size, mtime_ns):
            return 0, False, (size, mtime_ns)
        if lazy and not was_known:  # written here, not pushed yet (the folder starts empty):
            return 0, False, None  # it supersedes the recorded version, and the next push publishes it
    except OSError:
        pass
    hit = False
    try:
        if cas is not None and ref is not None and ref.sha256:
            hit = cas.materialise(ref.sha256, size, lambda tmp: store.get_file(key, tmp), local)
        else:
            store.get_file(key, local)
    except FileNotFoundError:
        raise InputError(f"{store.describe()}: {key}", f"recorded object of {rel} is missing") from None
    except ValueError as exc:
        raise InputError(f"{store.describe()}: {key}", f"recorded object of {rel}: {exc}") from None
    os.utime(local, ns=(mtime_ns, mtime_ns))
    return 1, bool(hit), (size, mtime_ns)
