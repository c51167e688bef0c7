"""Reading one patch of a tile's Parquet store by byte ranges, so a worker on S3 fetches only the row
groups that patch's rows lie in (the patch index ``patches.parquet`` gives the row range; Parquet's footer
gives each row group's byte range). Contract of the store: :mod:`storage.patches`.

Bytes fetched for one patch ~ footer (pyarrow reads the last 64 KiB first) + the patches table + the
row groups the patch overlaps, against the whole ``points.parquet`` for a whole-file read.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from storage.errors import InputError
from storage.grid import PatchGrid
from storage.ids import PatchId
from storage.objstore.store import Store
from storage.patches.read import _RowGroupFile
from storage.patches.schema import (
    FACE_DTYPES,
    FACES_FILE,
    META_KEY,
    PATCH_DTYPES,
    PATCHES_FILE,
    POINT_DTYPES,
    POINTS_FILE,
    SCHEMA_VERSION,
    table_columns,
)

_TABLES = {"points": (POINTS_FILE, POINT_DTYPES, "point"), "faces": (FACES_FILE, FACE_DTYPES, "face")}


class RangeFile(io.RawIOBase):
    """A read-only seekable file over one store object; each ``read`` is one ranged GET.

    ``bytes_fetched`` / ``requests`` count what went over the wire (a local store reads the file).
    """

    def __init__(self, store: Store, key: str, size: int | None = None):
        super().__init__()
        self.store, self.key = store, key
        self.size = store.size(key) if size is None else int(size)
        self.pos, self.bytes_fetched, self.requests = 0, 0, 0

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.size}[whence]
        self.pos = max(0, base + offset)
        return self.pos

    def readinto(self, b) -> int:
        end = min(self.size, self.pos + len(b))
        if end <= self.pos:
            return 0
        data = self.store.get_range(self.key, self.pos, end)
        n = len(data)
        b[:n] = data
        self.pos += n
        self.bytes_fetched += n
        self.requests += 1
        return n


def open_ranged(store: Store, key: str, buffer_size: int = 1 << 16) -> io.BufferedReader:
    """A buffered read-only file over one store object for readers that take a file object (laspy for
    LAS/LAZ: its header, VLRs and the LAZ chunk table come in a few ranged GETs, then only the chunks
    read). ``.raw`` is the :class:`RangeFile` with the byte and request counters."""
    return io.BufferedReader(RangeFile(store, key), buffer_size=buffer_size)


@dataclass(frozen=True)
class PatchRows:
    """One patch's rows of one table, and what reading them cost.

    columns: column name -> (n,) array in store dtypes; file_size: bytes of the table's file;
    bytes_fetched / requests: of the table file alone (+ ``index_bytes`` for patches.parquet).
    """

    key: int
    columns: dict[str, np.ndarray] = field(repr=False)
    row_groups_read: int
    file_size: int
    bytes_fetched: int
    requests: int
    index_bytes: int


def _check_meta(pf: pq.ParquetFile, table: str, where: str) -> dict:
    raw = (pf.schema_arrow.metadata or {}).get(META_KEY)
    try:
        meta = json.loads(raw) if raw is not None else {}
    except ValueError:
        meta = {}
    if meta.get("schema_version") != SCHEMA_VERSION or meta.get("table") != table:
        raise InputError(where, f"not a v{SCHEMA_VERSION} {table} table of the ms3d patch store "
                                f"(schema_version {meta.get('schema_version')!r}, table {meta.get('table')!r})")
    return meta


def read_patch_index(store: Store, tile_key: str) -> tuple[dict[str, np.ndarray], int]:
    """A tile's patches table (one GET: it is small) as columns (PATCH_DTYPES), and its size in bytes."""
    key = f"tiles/{tile_key}/{PATCHES_FILE}"
    where = f"{store.describe()}: {key}"
    try:
        data = store.get(key)
    except FileNotFoundError:
        raise InputError(where, "missing (patches table of the patch store)") from None
    try:
        pf = pq.ParquetFile(pa.BufferReader(data))
        _check_meta(pf, "patches", where)
        return table_columns(pf.read(), PATCH_DTYPES, PATCH_DTYPES), len(data)
    except (OSError, pa.ArrowException) as exc:
        raise InputError(where, f"not a readable Parquet file ({exc})") from None


def read_patch_rows(store: Store, tile_key: str, patch: int | PatchId, table: str = "points",
                    columns=None, index: dict[str, np.ndarray] | None = None) -> PatchRows:
    """One patch's rows of a tile's ``points`` or ``faces`` table, fetching only its row groups.

    Args:
        store: the work dir's store; the tile lives under ``tiles/{tile_key}/``.
        patch: packed int64 key or PatchId. KeyError when the tile has no such patch.
        columns: subset of the table's columns (default all).
        index: the tile's patches table when the caller already holds it (saves one GET).
    """
    if table not in _TABLES:
        raise ValueError(f"table must be one of {list(_TABLES)}, not {table!r}")
    index_bytes = 0
    if index is None:
        index, index_bytes = read_patch_index(store, tile_key)
    want = PatchGrid.pack(np.array([[patch.i, patch.j, patch.k]]))[0] if isinstance(patch, PatchId) else patch
    row = int(np.searchsorted(index["patch"], want))
    if row >= len(index["patch"]) or index["patch"][row] != want:
        raise KeyError(f"patch {patch} not in tile {tile_key}")
    file_name, dtypes, side = _TABLES[table]
    key = f"tiles/{tile_key}/{file_name}"
    where = f"{store.describe()}: {key}"
    try:
        f = RangeFile(store, key)
    except FileNotFoundError:
        raise InputError(where, f"missing ({table} table of the patch store)") from None
    try:
        pf = pq.ParquetFile(f, pre_buffer=True)
        _check_meta(pf, table, where)
        ranges = np.array([[index[f"{side}_start"][row], index[f"{side}_stop"][row]]], dtype=np.int64)
        data, local, groups = _RowGroupFile(pf, where, dtypes).read(ranges, columns)
    except (OSError, pa.ArrowException) as exc:
        raise InputError(where, f"cannot read by ranges ({store.redact(str(exc))})") from None
    n = int(ranges[0, 1] - ranges[0, 0])
    cols = {c: v[local[0]:local[0] + n] for c, v in data.items()}
    return PatchRows(int(want), cols, groups, f.size, f.bytes_fetched, f.requests, index_bytes)
