"""The single-run lock of a work dir on an object store: a lease, taken by a conditional create.

A local work dir keeps its ``flock`` lock (:func:`storage.workdir.housekeeping.work_dir_lock`): the OS releases
it when the process dies. An object store has no flock, so the lock is one small object, ``.lock.json``:

- **take**: ``PUT If-None-Match: *`` with ``{owner, token, expires_utc}``; exactly one of racing runs wins.
- **renew**: ``PUT If-Match: <etag of our last write>`` with a later expiry; it fails if anyone else
  wrote the object since (our lease was taken over), and then the holder must stop.
- **take over**: when the object's expiry has passed (its holder crashed and stopped renewing), a run
  replaces it with ``PUT If-Match: <etag it read>``; of several contenders only one can match.
- **release**: ``DELETE If-Match: <our etag>``, so a run never deletes a lease that is no longer its own.

Expiry is judged on the contender's clock against the holder's written ``expires_utc``: keep ``ttl_s``
well above the clock skew between machines (NTP keeps it to well under a second).
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass

from storage.errors import InputError, Ms3dError
from storage.objstore.honest import check_conditional_writes
from storage.objstore.store import PreconditionFailed, Store
from storage.workdir.housekeeping import work_dir_lock
from storage.workdir.layout import WorkDir

LOCK_KEY = ".lock.json"
DEFAULT_TTL_S = 60.0


class LeaseLost(Ms3dError):
    """Our lease was taken over (we did not renew it in time): stop writing to the work dir."""


def default_owner() -> str:
    return f"{socket.gethostname()} pid {os.getpid()}"


@dataclass
class Lease:
    """A held lease: ``etag`` of our last write, ``expires_utc`` epoch seconds."""

    store: Store
    owner: str
    token: str
    ttl_s: float
    etag: str
    expires_utc: float
    lost: LeaseLost | InputError | None = None

    def check(self) -> None:
        """Raise if the background renewal found the lease lost (call between units of work)."""
        if self.lost is not None:
            raise self.lost

    def _body(self, expires: float) -> bytes:
        return json.dumps({"owner": self.owner, "token": self.token, "expires_utc": expires,
                           "ttl_s": self.ttl_s}).encode()

    def renew(self, now: float | None = None) -> None:
        """Push the expiry to now + ttl_s. Raises LeaseLost when another run wrote the lock since."""
        expires = (time.time() if now is None else now) + self.ttl_s
        body = self._body(expires)
        try:
            self.etag = self.store.put_if_match(LOCK_KEY, body, self.etag)
        except PreconditionFailed:
            # a renewal whose response was lost (a transient error) may have landed: then the lock
            # still holds our token under an ETag we never saw; adopt it and renew once more
            current = self.store.get_with_etag(LOCK_KEY)
            if current is None or _token(current[0]) != self.token:
                raise LeaseLost(f"{self.store.describe()}: the run lock was taken over by another run") from None
            try:
                self.etag = self.store.put_if_match(LOCK_KEY, body, current[1])
            except PreconditionFailed:
                raise LeaseLost(f"{self.store.describe()}: the run lock was taken over by another run") from None
        self.expires_utc = expires

    def release(self) -> bool:
        """Delete the lock if it is still ours; False when it was taken over meanwhile."""
        return self.store.delete_if_match(LOCK_KEY, self.etag)


def _token(raw: bytes) -> str | None:
    try:
        return str(json.loads(raw)["token"])
    except (ValueError, KeyError, TypeError):
        return None


def _holder(raw: bytes) -> dict:
    try:
        d = json.loads(raw)
        return {"owner": str(d["owner"]), "expires_utc": float(d["expires_utc"])}
    except (ValueError, KeyError, TypeError):
        return {"owner": "unreadable lock", "expires_utc": 0.0}  # a garbled lock is treated as expired


def acquire_lease(store: Store, owner: str | None = None, ttl_s: float = DEFAULT_TTL_S,
                  now: float | None = None) -> Lease:
    """Take the store's run lock, or take over an expired one.

    Raises InputError (one line, naming the holder and its expiry) when a live lease is held, or when the
    endpoint does not honour conditional writes (:mod:`storage.objstore.honest`)."""
    check_conditional_writes(store)
    owner = owner or default_owner()
    now = time.time() if now is None else now
    lease = Lease(store, owner, uuid.uuid4().hex, ttl_s, "", now + ttl_s)
    body = lease._body(lease.expires_utc)
    try:
        lease.etag = store.put_if_absent(LOCK_KEY, body)
        return lease
    except PreconditionFailed:
        pass
    current = store.get_with_etag(LOCK_KEY)
    if current is None:  # released between our two calls: one more conditional create decides
        try:
            lease.etag = store.put_if_absent(LOCK_KEY, body)
            return lease
        except PreconditionFailed:
            current = store.get_with_etag(LOCK_KEY) or (b"{}", "")
    raw, etag = current
    holder = _holder(raw)
    if holder["expires_utc"] > now:
        left = holder["expires_utc"] - now
        raise InputError(store.describe(), f"the work dir is in use by another ms3d run ({holder['owner']}; "
                                           f"its lease expires in {left:.0f} s unless renewed); wait for it to end")
    try:
        lease.etag = store.put_if_match(LOCK_KEY, body, etag)
    except PreconditionFailed:
        raise InputError(store.describe(), "another ms3d run took over the expired run lock first") from None
    return lease


class _Renewer(threading.Thread):
    """Renews a lease every ttl_s / 3 until stopped; remembers a lost lease for the holder to raise.

    A transient failure (InputError: network, 5xx, throttling) is retried with a doubling backoff
    (from ttl_s / 30, at most ttl_s / 10) while more than ``GIVE_UP_FRACTION`` of the TTL is left
    before the expiry we last wrote; only then is the lease recorded lost. LeaseLost (another run
    wrote the lock) is recorded at once."""

    GIVE_UP_FRACTION = 0.25

    def __init__(self, lease: Lease, clock=time.time):
        super().__init__(name="ms3d-lease-renewer", daemon=True)
        self.lease, self.stop_event, self.error, self.clock = lease, threading.Event(), None, clock
        self.transient_failures = 0

    def run(self) -> None:
        ttl = self.lease.ttl_s
        wait, backoff = ttl / 3, ttl / 30
        while not self.stop_event.wait(wait):
            try:
                self.lease.renew()
            except LeaseLost as exc:
                self.error = self.lease.lost = exc
                return
            except InputError as exc:
                self.transient_failures += 1
                left = self.lease.expires_utc - self.clock() - self.GIVE_UP_FRACTION * ttl
                if left <= 0:
                    self.error = self.lease.lost = exc
                    return
                wait, backoff = min(backoff, left), min(2 * backoff, ttl / 10)
                continue
            wait, backoff = ttl / 3, ttl / 30


@contextlib.contextmanager
def run_lock(store: Store, owner: str | None = None, ttl_s: float = DEFAULT_TTL_S) -> Iterator[Lease | None]:
    """Hold the work dir's single-run lock for a ``with`` block.

    Local store: the existing flock lock (yields None). Object store: a lease renewed in the background
    (yields the :class:`Lease`); raises LeaseLost at exit if the lease was lost during the block.
    """
    if store.is_local:
        with work_dir_lock(WorkDir(store.root)):
            yield None
        return
    lease = acquire_lease(store, owner, ttl_s)
    renewer = _Renewer(lease)
    renewer.start()
    try:
        yield lease
    finally:
        renewer.stop_event.set()
        renewer.join()
        if renewer.error is None:
            lease.release()
    if renewer.error is not None:
        raise renewer.error
