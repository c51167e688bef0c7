"""The statements of an OBJ file parsed into arrays: a block parser for photogrammetry OBJs (C CSV reader,
no loop per line) and a line-by-line parser for any other; :func:`storage.formats.obj.read_obj` builds the mesh."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.errors import InputError


def _numbers(rows: list[str], dtype=np.float64) -> np.ndarray | None:
    """All whitespace-separated numbers of ``rows``, flat, parsed in C; None if any token is not one."""
    try:
        return np.fromstring(" ".join(rows), sep=" ", dtype=dtype)
    except ValueError:
        return None


def _table(path: Path, rows: list[str], widths: tuple[int, ...], what: str) -> np.ndarray:
    """(len(rows), w) float64 for the first width w that fits every row; else the first ``widths[-1]``
    columns of each row (rows shorter than that are an error)."""
    nums = _numbers(rows)
    for width in widths:
        if nums is not None and nums.size == width * len(rows):
            return nums.reshape(len(rows), width)
    keep = min(widths)
    try:
        return np.array([r.split()[:keep] for r in rows], dtype=np.float64).reshape(len(rows), keep)
    except ValueError as err:
        raise InputError(path, f"malformed {what} statement ({err})") from err


def _face_corners(path: Path, rows: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Face statements -> (corner count per face, raw v id per corner, raw vt id per corner or None).

    Ids are as written (1-based, or negative = relative); a corner without a vt gets vt 0. Files of
    triangles in one layout ('v', 'v/vt', 'v//vn', 'v/vt/vn') are parsed in C; others token by token.
    """
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), None
    if rows[0] != rows[0].strip() or rows[-1] != rows[-1].strip():
        rows = [r.strip() for r in rows]
    token = rows[0].split()[0]
    slashes = token.count("/")
    has_vt = slashes >= 1 and token.split("/")[1] != ""
    per_corner = 1 + slashes - (1 if slashes == 2 and not has_vt else 0)
    joined = " ".join(rows)
    n = len(rows)
    if joined.count(" ") == 3 * n - 1 and joined.count("/") == 3 * n * slashes:
        nums = _numbers([joined.replace("/", " ")], np.int64)
        if nums is not None and nums.size == 3 * n * per_corner:
            ids = nums.reshape(3 * n, per_corner)
            return np.full(n, 3, np.int64), ids[:, 0], (ids[:, 1] if has_vt else None)
    split = [r.split() for r in rows]
    counts = np.array([len(r) for r in split], dtype=np.int64)
    parts = [t.split("/") for t in itertools.chain.from_iterable(split)]
    try:
        v = np.array([p[0] for p in parts], dtype=np.int64)
        vt = np.array([int(p[1]) if len(p) > 1 and p[1] else 0 for p in parts], dtype=np.int64)
    except ValueError as err:
        raise InputError(path, f"malformed face statement ({err})") from err
    return counts, v, (vt if vt.any() else None)


def resolve_ids(raw: np.ndarray, seen: np.ndarray | None) -> np.ndarray:
    """OBJ ids (1-based, or negative = relative to the ``seen`` elements so far) -> 0-based; 0 -> -1."""
    relative = raw + seen if seen is not None else np.full_like(raw, -1)
    return np.where(raw > 0, raw - 1, np.where(raw < 0, relative, -1))


def seen_before_faces(lines: list[str], key: str) -> np.ndarray:
    """For each face statement, how many ``key`` statements precede it (for negative OBJ ids)."""
    seen, n = [], 0
    for ln in lines:
        k = ln.partition(" ")[0]
        if k == key:
            n += 1
        elif k == "f":
            seen.append(n)
    return np.array(seen, dtype=np.int64)


@dataclass
class Statements:
    """The parsed statements of an OBJ: xyzc (n, 3|4|6) float64 vertex rows, vt (k, 2|3) float64, counts
    (f,) corners per face, raw_v / raw_vt (sum(counts),) ids as written (raw_vt None without uvs),
    usemtl names with the number of faces before each, mtllib arguments, and the text lines (kept
    only when an id is negative, for relative ids)."""

    xyzc: np.ndarray
    vt: np.ndarray
    counts: np.ndarray
    raw_v: np.ndarray
    raw_vt: np.ndarray | None
    usemtl_names: list[str]
    faces_before_usemtl: list[int]
    mtllibs: list[str]
    lines: list[str] | None = None


_V, _VT, _F, _VN, _OTHER = 1, 2, 3, 4, 0


def _line_kinds(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start offset of every line of ``buf`` ((n,) int64) and its statement kind ((n,) int8)."""
    nl = np.flatnonzero(buf == 10)
    starts = np.concatenate(([0], nl + 1))
    if starts[-1] >= len(buf):
        starts = starts[:-1]
    c0 = buf[starts]
    c1 = buf[np.minimum(starts + 1, len(buf) - 1)]
    c2 = buf[np.minimum(starts + 2, len(buf) - 1)]
    kind = np.zeros(len(starts), np.int8)
    kind[(c0 == ord("v")) & ((c1 == 32) | (c1 == 9))] = _V
    kind[(c0 == ord("v")) & (c1 == ord("t")) & ((c2 == 32) | (c2 == 9))] = _VT
    kind[(c0 == ord("v")) & (c1 == ord("n")) & ((c2 == 32) | (c2 == 9))] = _VN
    kind[(c0 == ord("f")) & ((c1 == 32) | (c1 == 9))] = _F
    return starts, kind


def _csv_block(block: bytes, columns: list[int], dtype) -> np.ndarray | None:
    """Columns of a block of space-separated statements, parsed by pandas' C reader (~6x numpy's
    fromstring); None when the block is not a clean table (the caller then parses line by line)."""
    import io

    import pandas as pd

    try:
        df = pd.read_csv(io.BytesIO(block), sep=" ", header=None, usecols=columns, engine="c",
                         skipinitialspace=True, dtype=np.float64)
    except (ValueError, pd.errors.ParserError):
        return None
    out = df.to_numpy(np.float64)
    if out.shape[1] != len(columns) or (dtype != np.float64 and not np.isfinite(out).all()):
        return None  # integer columns with gaps (a 'v//vn' layout, ragged rows)
    return out if dtype == np.float64 else out.astype(dtype)


def fast_statements(data: bytes) -> Statements | None:
    """Parse an OBJ written in blocks (all ``v``, all ``vt``, runs of triangle ``f`` statements, as
    photogrammetry tools write them) without a Python loop per line; None for anything else (polygons,
    negative ids, ragged rows), which the line-by-line parser handles."""
    buf = np.frombuffer(data, np.uint8)
    if len(buf) == 0:
        return None
    starts, kind = _line_kinds(buf)
    ends = np.append(starts[1:], len(buf))
    cut = np.flatnonzero(np.diff(kind)) + 1
    run_lo, run_hi = np.concatenate(([0], cut)), np.concatenate((cut, [len(kind)]))
    parts: dict[int, list[np.ndarray]] = {_V: [], _VT: [], _F: []}
    usemtl, before, mtllibs, n_faces = [], [], [], 0
    for lo, hi in zip(run_lo, run_hi):  # one iteration per run of like statements (a handful)
        k = int(kind[lo])
        block = data[starts[lo]:ends[hi - 1]]
        if k == _OTHER:
            for line in block.decode(errors="replace").replace("\t", " ").splitlines():
                key, _, rest = line.strip().partition(" ")
                if key == "usemtl":
                    usemtl.append(rest.strip())
                    before.append(n_faces)
                elif key == "mtllib":
                    mtllibs.append(rest.strip())
            continue
        if k == _VN:
            continue
        first = data[starts[lo]:ends[lo]].split()
        if k == _F:
            if len(first) != 4 or b"-" in block:
                return None  # polygons or relative ids
            per = first[1].count(b"/") + 1
            if per == 3 and b"//" in first[1]:
                return None
            block = block.replace(b"/", b" ")
            cols = list(range(1, 1 + 3 * per))
            got = _csv_block(block, cols, np.int64)
            if got is None or len(got) != hi - lo:
                return None
            parts[_F].append(got.reshape(-1, per))
            n_faces += hi - lo
        else:
            width = len(first) - 1
            got = _csv_block(block, list(range(1, 1 + width)), np.float64)
            if got is None or len(got) != hi - lo:
                return None
            parts[k].append(got)
    widths = {p.shape[1] for p in parts[_F]}
    if len(widths) > 1 or any(len({p.shape[1] for p in parts[k]}) > 1 for k in (_V, _VT)):
        return None
    xyzc = np.concatenate(parts[_V]) if parts[_V] else np.zeros((0, 3))
    vt = np.concatenate(parts[_VT]) if parts[_VT] else np.zeros((0, 2))
    ids = np.concatenate(parts[_F]) if parts[_F] else np.zeros((0, 1), np.int64)
    return Statements(xyzc, vt, np.full(n_faces, 3, np.int64), ids[:, 0].copy(),
                       ids[:, 1].copy() if ids.shape[1] >= 2 else None, usemtl, before, mtllibs)


def slow_statements(path: Path, text: str) -> Statements:
    """Line by line (any valid OBJ): one pass to bucket the statements, each bucket parsed in bulk."""
    lines = text.replace("\t", " ").splitlines()
    rows: dict[str, list[str]] = {"v": [], "vt": [], "f": [], "mtllib": []}
    usemtl_names, faces_before_usemtl = [], []
    for ln in lines:
        key, _, rest = ln.partition(" ")
        bucket = rows.get(key)
        if bucket is not None:
            bucket.append(rest)
        elif key == "usemtl":
            usemtl_names.append(rest.strip())
            faces_before_usemtl.append(len(rows["f"]))
    xyzc = _table(path, rows["v"], (3, 6, 4), "vertex")
    vt = _table(path, rows["vt"], (2, 3), "texture coordinate")
    counts, raw_v, raw_vt = _face_corners(path, rows["f"])
    return Statements(xyzc, vt, counts, raw_v, raw_vt, usemtl_names, faces_before_usemtl,
                       [r.strip() for r in rows["mtllib"]], lines)
