"""Labels a user gives in the viewer (``ms3d view WORKDIR --label``): ``WORKDIR/labels/user-<date>.csv``.

One CSV per UTC day, header ``i,j,k,label,time``; one row per click: the patch cell (``PatchId`` of
:class:`storage.grid.PatchGrid`, world-anchored, so a row stays valid whatever the campus extent), the label
(0 good, 1 bad) and the ISO 8601 UTC time of the click. Rows are only appended; a later row for the same
patch overrides an earlier one when the labels are read (the user changed their mind).

>>> parse_label_request(b'{"i": 3, "j": -4, "k": 5, "label": 1}')
((3, -4, 5), 1)
>>> parse_label_request(b'{"i": 3, "j": -4, "k": 5, "label": 2}')
Traceback (most recent call last):
...
ValueError: label must be 0 (good) or 1 (bad), got 2
"""

from __future__ import annotations

import csv
import datetime as dt
import json
import threading
from functools import lru_cache
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.grid import PatchGrid

LABELS_DIR = "labels"
HEADER = ("i", "j", "k", "label", "time")
_LOCK = threading.Lock()  # one writer per process: the view server's handler threads


def _strict_int(v, name: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{name} must be an integer, got {v!r}")  # noqa: TRY004 - a bad request, one line
    return v


def parse_label_request(body: bytes) -> tuple[tuple[int, int, int], int]:
    """A POSTed label ``{"i": int, "j": int, "k": int, "label": 0|1}`` -> ((i, j, k), label).

    Raises ValueError with one line saying what is wrong (not JSON, a missing key, a non-integer, a label
    outside {0, 1}, a cell out of range)."""
    try:
        doc = json.loads(body.decode("utf-8"))
    except (UnicodeDecodeError, ValueError):
        raise ValueError("body is not JSON") from None
    if not isinstance(doc, dict):
        raise ValueError("body must be a JSON object with i, j, k, label")  # noqa: TRY004 - a bad request, one line
    missing = [k for k in ("i", "j", "k", "label") if k not in doc]
    if missing:
        raise ValueError(f"missing {', '.join(missing)}")
    ijk = tuple(_strict_int(doc[k], k) for k in "ijk")
    try:
        PatchGrid.pack(np.array([ijk], np.int64))
    except ValueError:
        raise ValueError(f"cell {ijk} is beyond the patch grid's range") from None
    label = _strict_int(doc["label"], "label")
    if label not in (0, 1):
        raise ValueError(f"label must be 0 (good) or 1 (bad), got {label}")
    return ijk, label  # type: ignore[return-value]


def user_labels_path(work_dir: str | Path, when: dt.datetime) -> Path:
    """``WORKDIR/labels/user-YYYY-MM-DD.csv`` of the UTC day of ``when``."""
    return Path(work_dir) / LABELS_DIR / f"user-{when.astimezone(dt.UTC):%Y-%m-%d}.csv"


def append_user_label(work_dir: str | Path, ijk: tuple[int, int, int], label: int,
                      when: dt.datetime | None = None) -> Path:
    """Append one row (writing the header first for a new file); returns the CSV's path. Appends are whole
    lines written under a lock and flushed, so a reader never sees half a row from this process."""
    when = when or dt.datetime.now(dt.UTC)
    path = user_labels_path(work_dir, when)
    row = [*map(int, ijk), int(label), when.astimezone(dt.UTC).isoformat(timespec="seconds")]
    with _LOCK:
        path.parent.mkdir(parents=True, exist_ok=True)
        new = not path.exists() or path.stat().st_size == 0
        with open(path, "a", newline="") as f:
            w = csv.writer(f)
            if new:
                w.writerow(HEADER)
            w.writerow(row)
    return path


def _read_one(path: Path) -> list[tuple[int, int, int, int, str]]:
    try:
        rows = list(csv.reader(path.read_text().splitlines()))
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read ({exc})") from None
    out = []
    for n, r in enumerate(rows, start=1):
        if not r or [c.strip().lower() for c in r] == list(HEADER) or r[0].lstrip().startswith("#"):
            continue
        if len(r) != 5:
            raise InputError(path, f"line {n}: expected i,j,k,label,time, got {len(r)} columns")
        try:
            i, j, k, lab = (int(c) for c in r[:4])
        except ValueError:
            raise InputError(path, f"line {n}: non-integer value in {','.join(r[:4])!r}") from None
        if lab not in (0, 1):
            raise InputError(path, f"line {n}: label must be 0 (good) or 1 (bad), got {lab}")
        out.append((i, j, k, lab, r[4].strip()))
    return out


def read_user_labels(work_dir: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Every ``labels/*.csv`` of the work dir with the ``i,j,k,label,time`` header, the latest row of each
    patch winning (by time, then by file and line order).

    Returns ((u,) int64 packed keys sorted ascending, (u,) int8 labels)."""
    rows = []
    for path in sorted((Path(work_dir) / LABELS_DIR).glob("*.csv")):
        rows.extend(_read_one(path))
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int8)
    order = sorted(range(len(rows)), key=lambda r: (rows[r][4], r))  # stable: later lines win ties
    latest: dict[tuple[int, int, int], int] = {}
    for r in order:
        latest[rows[r][:3]] = rows[r][3]
    ijk = np.array(list(latest), np.int64).reshape(-1, 3)
    keys = PatchGrid.pack(ijk)
    labels = np.array(list(latest.values()), np.int8)
    o = np.argsort(keys)
    return keys[o], labels[o]


def _folder_state(work_dir: Path) -> tuple:
    d = work_dir / LABELS_DIR
    if not d.is_dir():
        return ()
    return tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(d.glob("*.csv")))


@lru_cache(maxsize=4)
def _labels(work_dir: str, state: tuple) -> tuple[np.ndarray, np.ndarray]:
    return read_user_labels(work_dir) if state else (np.zeros(0, np.int64), np.zeros(0, np.int8))


def tile_user_labels(work_dir: str | Path, grid: PatchGrid, tile: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The user's labels of the patches in ``tile`` (ix, iy): ((u,) int64 packed keys ascending, (u,) int8 0/1).
    Raises storage.errors.InputError naming the CSV when a labels file is malformed."""
    work_dir = Path(work_dir)
    keys, labels = _labels(str(work_dir), _folder_state(work_dir))
    if not len(keys):
        return keys, labels
    t = grid.tile_of_keys(keys)
    sel = (t[:, 0] == tile[0]) & (t[:, 1] == tile[1])
    return keys[sel], labels[sel]
