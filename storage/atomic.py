"""Atomic file writes: write to a temporary name in the same folder, then rename into place.

A reader therefore never sees a half-written file, and a crash leaves the previous version intact.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from storage import recorded
from storage.errors import InputError

_UMASK = os.umask(0)
os.umask(_UMASK)


@contextlib.contextmanager
def atomic_path(path: str | Path, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``, on error remove it.

    The temporary name keeps the final suffix (or ``suffix``) so writers that infer the format
    from the extension (laspy, trimesh, pyarrow) still work.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sfx = suffix if suffix is not None else "".join(path.suffixes)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=f".tmp{sfx}", dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, 0o666 & ~_UMASK)  # mkstemp makes 0600; published files get the usual mode
        os.replace(tmp_path, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_parts_atomic(path: str | Path, parts: Iterable) -> int:
    """Write bytes-like ``parts`` one after the other (never joined in memory) atomically; returns the bytes."""
    n = 0
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        for part in parts:
            n += f.write(part)
    return n


def write_json_atomic(path: str | Path, obj, indent: int = 2) -> None:
    write_bytes_atomic(path, (json.dumps(obj, indent=indent, sort_keys=False) + "\n").encode())


def file_sha256(path: str | Path, chunk: int = 1 << 22) -> str:
    """SHA-256 of a file's bytes, streamed in 4 MiB chunks; a file of a work dir on a bucket that this process
    holds as recorded (or has not downloaded) answers from its record (:mod:`storage.recorded`)."""
    if (known := recorded.recorded_digest(path, "sha256")) is not None:
        return known
    recorded.ensure_local(path)
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def file_fingerprint(path: str | Path) -> str:
    """A cheap content fingerprint for resume decisions: size + mtime_ns + sha256 of the first and
    last MiB. Exact checksums (``file_sha256``) are used where identity matters (synth manifests). A file
    of a work dir on a bucket held as recorded answers from its record (the pushing process computed it
    with :func:`local_file_fingerprint`)."""
    if (known := recorded.recorded_digest(path, "fingerprint")) is not None:
        return known
    recorded.ensure_local(path)
    return local_file_fingerprint(path)


def local_file_fingerprint(path: str | Path) -> str:
    """:func:`file_fingerprint` of the local file ``path``, from its bytes."""
    path = Path(path)
    st = path.stat()
    h = hashlib.sha256(f"{st.st_size}:{st.st_mtime_ns}".encode())
    with open(path, "rb") as f:
        h.update(f.read(1 << 20))
        if st.st_size > (2 << 20):
            f.seek(-(1 << 20), os.SEEK_END)
            h.update(f.read(1 << 20))
    return h.hexdigest()[:32]


def read_json(path: Path, missing: str) -> dict:
    """The JSON document at ``path``, as :func:`write_json_atomic` wrote it. InputError naming the file when
    it does not exist (``missing``: the problem and what to do) or is not valid JSON."""
    if not path.exists():
        raise InputError(path, missing)
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(path, f"corrupt JSON ({e})") from None
