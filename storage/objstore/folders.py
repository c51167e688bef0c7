"""Where each thread of each process keeps its mirror of a work dir on a bucket, and sweeping the folders of
process instances that are gone (:mod:`storage.objstore.mirror`).

A folder is ``{cache}/work/{url hash}-{pid}-{process instance}-{thread}``: a restarted process reuses its pid,
never its instance token, so it never publishes a killed instance's unpushed files.

>>> mirror_folder("s3://b/w", "/scratch", "ab12cd34").parent.as_posix()
'/scratch/work'
"""

from __future__ import annotations

import hashlib
import os
import threading
from pathlib import Path


def url_hash(url: str) -> str:
    return hashlib.sha256(url.encode()).hexdigest()[:12]


def mirror_folder(url: str, cache: str | Path, instance: str) -> Path:
    """This thread's mirror folder of the work dir ``url`` under ``cache`` for the process instance ``instance``."""
    return Path(cache) / "work" / f"{url_hash(url)}-{os.getpid()}-{instance}-{threading.get_ident()}"


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale_folders(url: str, cache: str | Path, instance: str) -> int:
    """Delete the mirror folders of ``url`` under ``cache`` that belong to no live process instance: another
    instance of this pid than ``instance`` (a restarted process) or a pid that is gone. Returns how many."""
    import shutil

    base, mine, gone = Path(cache) / "work", f"{os.getpid()}-{instance}", 0
    for d in base.glob(f"{url_hash(url)}-*") if base.is_dir() else []:
        parts = d.name.split("-")
        if len(parts) < 4 or not parts[1].isdigit():
            continue
        pid, inst = int(parts[1]), f"{parts[1]}-{parts[2]}"
        if inst != mine and (pid == os.getpid() or not _pid_alive(pid)):
            shutil.rmtree(d, ignore_errors=True)
            gone += 1
    return gone


__all__ = ["mirror_folder", "sweep_stale_folders", "url_hash"]
