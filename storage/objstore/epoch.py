"""Run epochs: commits fenced by the run, arbitrated by the store, never by wall clocks.

Each run that takes a work dir's lease on an object store begins an **epoch**: the next integer, created
with a conditional create (``PUT If-None-Match: *``) of ``epochs/{n:010d}.json``, so two runs can never
hold the same number. Every sync commit (:mod:`storage.objstore.mirror`) carries the epoch of the run it
belongs to, in its record key and its meta. The epoch object **seals** what came before: the record keys of
earlier epochs that were accepted when it was created. The reader's rule (:func:`accepted`):

- a record of the latest epoch ``E`` is accepted (the run in progress, or the last run);
- a record of an earlier epoch is accepted only if ``E``'s seal names it.

So a superseded run's late commit (written after the next run sealed its epoch) is ignored by every reader
and by every later run, whatever the writers' clocks say; its tasks learn it before they commit
(:func:`is_current`: one HEAD of the next epoch's key) and stop. Records of one epoch are ordered by their
Lamport counter (a writer's counter exceeds every counter it has read), not by time.

>>> epoch_key(3)
'epochs/0000000003.json'
>>> parse_record_unit("0000000003-000000000007-ab12cd34")
(3, 7)
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass

from storage.errors import InputError
from storage.objstore.store import PreconditionFailed, Store

EPOCHS = "epochs"
_ATTEMPTS = 8
_UNIT = re.compile(r"^(\d{10})-(\d{12})-")


def epoch_key(n: int) -> str:
    return f"{EPOCHS}/{int(n):010d}.json"


def record_unit(epoch: int, lamport: int, suffix: str) -> str:
    """The unit id of a sync commit: sorts by (epoch, Lamport counter)."""
    return f"{int(epoch):010d}-{int(lamport):012d}-{suffix}"


def parse_record_unit(unit: str) -> tuple[int, int]:
    """(epoch, lamport) of a sync commit's unit id; (0, 0) for ids without them (commits written before run
    epochs existed: epoch 0, which the first epoch seals).

    >>> parse_record_unit("00000000000001733000000000-ab12cd34")
    (0, 0)
    """
    m = _UNIT.match(unit)
    return (int(m[1]), int(m[2])) if m else (0, 0)


@dataclass(frozen=True)
class Epoch:
    """One run's epoch: its number, the lease token that began it, and the earlier records it sealed."""

    number: int
    token: str
    sealed: frozenset[str]


def _epoch_numbers(store: Store) -> list[int]:
    out = []
    for info in store.list(EPOCHS):
        name = info.key.rsplit("/", 1)[-1]
        if name.endswith(".json") and name[:-5].isdigit():
            out.append(int(name[:-5]))
    return sorted(out)


def read_epoch(store: Store, n: int) -> Epoch | None:
    """Epoch ``n`` as stored; None when absent (or ``n`` is 0: no run has begun one)."""
    if n <= 0:
        return None
    try:
        d = json.loads(store.get(epoch_key(n)))
        return Epoch(int(d["epoch"]), str(d["token"]), frozenset(d.get("sealed", [])))
    except FileNotFoundError:
        return None
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{store.describe()}: {epoch_key(n)}", f"not a valid run epoch ({exc})") from None


def latest_epoch(store: Store) -> Epoch | None:
    """The latest epoch of the store (one LIST of ``epochs/`` and one GET); None before the first run."""
    numbers = _epoch_numbers(store)
    return read_epoch(store, numbers[-1]) if numbers else None


def accepted(record_keys, latest: Epoch | None) -> set[str]:
    """The record keys a reader accepts, by the rule of the module docstring (``record_keys``: sync record
    keys ``records/sync/{unit}.json``; ``latest``: the store's latest epoch, None before the first run)."""
    cur = latest.number if latest is not None else 0
    sealed = latest.sealed if latest is not None else frozenset()
    out = set()
    for key in record_keys:
        e, _ = parse_record_unit(key.rsplit("/", 1)[-1].removesuffix(".json"))
        if e == cur or key in sealed:
            out.add(key)
    return out


def begin_epoch(store: Store, token: str, record_keys) -> Epoch:
    """Begin the next epoch for the run holding lease ``token`` (call right after taking the lease): seal
    the records accepted now (``record_keys``: the sync record keys listed just before) and create
    ``epochs/{n}.json`` if absent. Returns the new :class:`Epoch`."""
    for _ in range(_ATTEMPTS):
        prev = latest_epoch(store)
        sealed = sorted(accepted(record_keys, prev))
        n = (prev.number if prev is not None else 0) + 1
        body = json.dumps({"epoch": n, "token": token, "sealed": sealed, "started_utc": time.time()}).encode()
        try:
            store.put_if_absent(epoch_key(n), body)
        except PreconditionFailed:
            continue  # another run began n meanwhile (it holds no lease we hold: read again and go on)
        return Epoch(n, token, frozenset(sealed))
    raise InputError(store.describe(), f"could not begin a run epoch after {_ATTEMPTS} attempts")


def is_current(store: Store, epoch: int) -> bool:
    """Whether no later epoch has begun (one HEAD): a run's task commits only while this holds."""
    return not store.exists(epoch_key(epoch + 1))


__all__ = ["EPOCHS", "Epoch", "accepted", "begin_epoch", "epoch_key", "is_current", "latest_epoch",
           "parse_record_unit", "read_epoch", "record_unit"]
