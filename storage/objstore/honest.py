"""Does an object-store endpoint honour conditional writes? Checked once per endpoint before a run leans on them.

The run lease (:mod:`storage.objstore.lock`) and the run epochs (:mod:`storage.objstore.epoch`) are decided by
the store alone: a create-if-absent (``PUT If-None-Match: *``) that exactly one writer wins, and a
compare-and-swap (``PUT If-Match: etag``) that fails once anyone else wrote. An endpoint that accepts the
headers and ignores them (older S3-compatible servers, some gateways and caches) would let two runs hold the
same work dir and each think its commits are the only ones. So before the first lease on an endpoint a run
probes it, on a key of its own under the work dir:

1. create-if-absent of a fresh key must succeed;
2. the same create-if-absent again must fail (412 Precondition Failed);
3. a compare-and-swap with a wrong ETag must fail;
4. a compare-and-swap with the right ETag must succeed;

then deletes the key. Any answer but these refuses the run with one line naming the endpoint and the check
that failed. The verdict is kept per endpoint for the process (a few requests per endpoint and process).
"""

from __future__ import annotations

import threading
import uuid

from storage.errors import InputError
from storage.objstore.store import PreconditionFailed, Store

PROBE_PREFIX = ".ms3d-probe"
_CHECKED: dict[str, bool] = {}
_LOCK = threading.Lock()


def check_conditional_writes(store: Store) -> None:
    """Refuse (InputError, one line) unless ``store``'s endpoint honours conditional writes (module doc).
    A local store needs no check (it is locked with flock, not leased)."""
    if store.is_local:
        return
    key = f"{store.describe()}"
    with _LOCK:
        if _CHECKED.get(key):
            return
    probe = f"{PROBE_PREFIX}-{uuid.uuid4().hex}"
    what = None
    try:
        etag = store.put_if_absent(probe, b"1")
        try:
            store.put_if_absent(probe, b"2")
            what = "a second create-if-absent (If-None-Match: *) of the same key succeeded"
        except PreconditionFailed:
            pass
        if what is None:
            try:
                store.put_if_match(probe, b"3", '"0000000000000000000000000000000f"')
                what = "a compare-and-swap (If-Match) with a wrong ETag succeeded"
            except PreconditionFailed:
                pass
        if what is None:
            try:
                store.put_if_match(probe, b"4", etag)
            except PreconditionFailed:
                what = "a compare-and-swap (If-Match) with the object's own ETag failed"
    except PreconditionFailed:
        what = "a create-if-absent (If-None-Match: *) of a fresh key failed"
    finally:
        try:
            store.delete([probe])
        except (InputError, OSError):
            pass
    if what is not None:
        raise InputError(store.describe(), f"the endpoint does not honour conditional writes ({what}); a run lease "
                                           "and fenced commits are impossible there: use an S3 endpoint that "
                                           "supports If-None-Match and If-Match on PUT")
    with _LOCK:
        _CHECKED[key] = True


__all__ = ["check_conditional_writes"]
