"""Keeping a work dir equal to what the current plan names: temporary files of killed runs, manifest
records of units that no longer exist, a lock against two runs at once, and a writable check.

After any change of inputs, a resumed run must leave the same files as a clean run: whatever the plan
does not name is removed (staging files in :func:`storage.contracts.staging.prune_staging`, stores of tiles that
lost their data in ``tasks.partition``, records here).
"""

from __future__ import annotations

import contextlib
import errno
import os
from collections.abc import Iterator

from storage.errors import InputError
from storage.workdir.layout import WorkDir

SWEPT_FOLDERS = ("staging", "tiles", "scan", "manifest.d", "report", "regions", "output")


def sweep_temporary_files(wd: WorkDir) -> int:
    """Remove the temporary files (``.{name}.*.tmp*``) a killed run left behind; returns how many.
    Call only while holding the work-dir lock (another run's temporary files are live)."""
    n = 0
    for name in SWEPT_FOLDERS + ("",):
        d = wd.root / name
        if not d.exists():
            continue
        files = d.glob(".*.tmp*") if name == "" else d.rglob(".*.tmp*")
        for p in files:
            if p.is_file():
                p.unlink(missing_ok=True)
                n += 1
    return n


def drop_unplanned_records(wd: WorkDir, stage: str, keep: set[str]) -> int:
    """Delete the manifest records of ``stage`` whose unit the plan no longer names."""
    d = wd.manifest_dir / stage
    n = 0
    if d.exists():
        for p in d.glob("*.json"):
            if p.stem not in keep:
                p.unlink(missing_ok=True)
                n += 1
    return n


def check_work_dir_writable(wd: WorkDir) -> None:
    """Raise InputError (one line) when the work dir cannot be created or written."""
    try:
        wd.root.mkdir(parents=True, exist_ok=True)
        probe = wd.root / f".write-probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        why = {errno.EACCES: "permission denied", errno.EROFS: "read-only file system",
               errno.ENOSPC: "no space left on the device"}.get(e.errno, e.strerror or str(e))
        raise InputError(wd.root, f"the work dir is not writable ({why}): choose another with --work-dir") from None


@contextlib.contextmanager
def work_dir_lock(wd: WorkDir) -> Iterator[None]:
    """Hold an exclusive lock on the work dir for a run (released by the OS if the process dies)."""
    import fcntl

    wd.root.mkdir(parents=True, exist_ok=True)
    path = wd.root / ".lock"
    f = open(path, "a+")
    try:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            other = f.read().strip() or "another process"
            raise InputError(wd.root, f"the work dir is in use by another ms3d run ({other}); wait for it to end") from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()}")
        f.flush()
        yield
    finally:
        f.close()

