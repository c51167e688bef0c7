"""Writing the patch store: a tile's three tables, its patches table alone, side tables, and the block-wise
:class:`TableWriter` (contract in :mod:`storage.patches`)."""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from storage.atomic import atomic_path
from storage.contracts.columns import arrow_array
from storage.patches.schema import (
    DEFAULT_ROW_GROUP_SIZE,
    DICT_COLUMNS,
    FACES_FILE,
    META_KEY,
    PATCHES_FILE,
    POINTS_FILE,
    RAW_COLUMNS,
    SCHEMAS,
    SIDE_TABLES,
    TABLE_SPECS,
    TileMeta,
    TileStoreSummary,
    side_table_path,
)


def _complete(cols: dict | None, table: str, where: Path) -> dict[str, np.ndarray]:
    """Columns in schema order and dtypes, defaults filled in. Raises ValueError for bad columns."""
    _, dtypes, defaults = TABLE_SPECS[table]
    cols = cols or {}
    unknown = sorted(set(cols) - set(dtypes))
    if unknown:
        raise ValueError(f"{where}: unknown {table} columns {unknown}; known: {list(dtypes)}")
    lengths = {len(np.asarray(v)) for v in cols.values()}
    if len(lengths) > 1:
        raise ValueError(f"{where}: {table} columns differ in length")
    n = lengths.pop() if lengths else 0
    out = {}
    for name, dt in dtypes.items():
        if name in cols:
            out[name] = _cast(np.asarray(cols[name]), dt, f"{where}: {table}.{name}")
        elif name in defaults:
            out[name] = np.full(n, defaults[name], dtype=dt)
        elif n == 0:
            out[name] = np.zeros(0, dtype=dt)
        else:
            raise ValueError(f"{where}: {table} column {name!r} is required")
    return out


def complete_columns(cols: dict | None, table: str, where: Path) -> dict[str, np.ndarray]:
    """Columns of ``table`` in schema order and store dtypes, defaults filled in (ValueError if bad)."""
    return _complete(cols, table, Path(where))


def write_patches_table(tile_dir: str | Path, patches_cols: dict, meta: TileMeta, n_points: int, n_faces: int) -> int:
    """Write a tile's ``patches.parquet`` (last: its presence marks a complete store), after checking that
    its row ranges account for the ``n_points`` / ``n_faces`` rows of the data tables. Returns bytes."""
    tile_dir = Path(tile_dir)
    patches = _complete(patches_cols, "patches", tile_dir)
    for side, n in (("point", n_points), ("face", n_faces)):
        count = patches[f"n_{side}s"]
        if not (np.array_equal(patches[f"{side}_stop"] - patches[f"{side}_start"], count) and count.sum() == n):
            raise ValueError(f"{tile_dir}: {side} ranges do not match the {n} rows written")
    return _write_table(tile_dir / PATCHES_FILE, patches, "patches",
                        meta.to_json("patches", len(patches["patch"]), points_rows=n_points, faces_rows=n_faces),
                        DEFAULT_ROW_GROUP_SIZE, "auto")


def _cast(a: np.ndarray, dt: np.dtype, what: str) -> np.ndarray:
    if a.ndim != 1:
        raise ValueError(f"{what}: expected a 1-d array, got shape {a.shape}")
    if a.dtype == dt:
        return a
    if dt.kind in "iub":
        if a.dtype.kind not in "iub":
            raise ValueError(f"{what}: expected {dt}, got {a.dtype}")
        if a.size and dt.kind != "b":
            info = np.iinfo(dt)
            if a.min() < info.min or a.max() > info.max:
                raise ValueError(f"{what}: values outside the range of {dt}")
    elif a.dtype.kind not in "iuf":
        raise ValueError(f"{what}: expected {dt}, got {a.dtype}")
    return a.astype(dt)


def _check_ranges(patches: dict, n_points: int, n_faces: int, points: dict, faces: dict, where: Path) -> None:
    """Cheap (per-patch, not per-row) consistency checks of the patches table against the data tables."""
    keys = patches["patch"]
    if len(keys) > 1 and not (keys[1:] > keys[:-1]).all():
        raise ValueError(f"{where}: patches.patch must be strictly ascending")
    for side, n, data in (("point", n_points, points), ("face", n_faces, faces)):
        start, stop = patches[f"{side}_start"], patches[f"{side}_stop"]
        count = patches[f"n_{side}s"]
        if not (np.array_equal(stop - start, count) and count.sum() == n and (count >= 0).all()):
            raise ValueError(f"{where}: {side} ranges do not match n_{side}s or the {n} rows written")
        filled = count > 0
        if filled.any():
            s = start[filled]
            if not (np.array_equal(data["patch"][s], keys[filled]) and
                    np.array_equal(data["patch"][stop[filled] - 1], keys[filled])):
                raise ValueError(f"{where}: {side} rows are not sorted by patch as the ranges say")
            if len(s) > 1 and not (s[1:] >= stop[filled][:-1]).all():
                raise ValueError(f"{where}: {side} ranges overlap")


def _compression(table: str, compression) -> str | dict:
    if compression != "auto":
        return compression
    return {name: ("none" if name in RAW_COLUMNS else "lz4") for name in TABLE_SPECS[table][1]} \
        if table in ("points", "faces") else "zstd"


def _write_table(path: Path, cols: dict, table: str, meta_json: dict, row_group_size: int, compression) -> int:
    with TableWriter(path, table, meta_json, row_group_size, compression) as w:
        w.write(cols)
    return path.stat().st_size


class TableWriter:
    """Write one store table block by block, atomically, with the row groups a one-shot write would have.

    Blocks of complete columns (already in store dtypes and patch order) are appended with
    :meth:`write`; rows are passed to Parquet only in whole row groups of ``row_group_size`` (the rest
    waits for the next block), so a table written in blocks is byte for byte the table written at once,
    and memory holds one block plus less than a row group. ``meta_json`` must state the final
    ``n_rows``; :meth:`close` checks it. The file appears at ``path`` only when the context exits cleanly.
    """

    def __init__(self, path: Path, table: str, meta_json: dict, row_group_size: int = DEFAULT_ROW_GROUP_SIZE,
                 compression="auto"):
        self.path, self.table, self.row_group_size = Path(path), table, row_group_size
        self.schema = SCHEMAS[table].with_metadata({META_KEY: json.dumps(meta_json).encode()})
        self.n_rows, self.expected = 0, meta_json.get("n_rows")
        self._carry: pa.Table | None = None
        self._compression = _compression(table, compression)
        self._dictionary = [c for c in DICT_COLUMNS if c in TABLE_SPECS[table][1]] if table in ("points", "faces") else True

    def __enter__(self) -> TableWriter:
        self._ctx = atomic_path(self.path)
        tmp = self._ctx.__enter__()
        self._writer = pq.ParquetWriter(tmp, self.schema, compression=self._compression,
                                        use_dictionary=self._dictionary,
                                        # min/max of the sorted keys locate a patch's row groups; bboxes
                                        # are per patch in patches.parquet (float statistics cost ~15 %)
                                        write_statistics=["patch"] if self.table in ("points", "faces") else True,
                                        sorting_columns=[pq.SortingColumn(self.schema.get_field_index("patch"))])
        return self

    def write(self, cols: dict[str, np.ndarray]) -> None:
        t = pa.Table.from_arrays([arrow_array(cols[f.name], f.type) for f in self.schema], schema=self.schema)
        self.n_rows += t.num_rows
        if self._carry is not None:
            t = pa.concat_tables([self._carry, t])
        whole = (t.num_rows // self.row_group_size) * self.row_group_size
        if whole:
            self._writer.write_table(t.slice(0, whole), row_group_size=self.row_group_size)
        self._carry = t.slice(whole) if whole < t.num_rows else None

    def __exit__(self, exc_type, exc, tb):
        try:
            if exc_type is None:
                if self._carry is not None:
                    self._writer.write_table(self._carry, row_group_size=self.row_group_size)
                elif self.n_rows == 0:
                    self._writer.write_table(self.schema.empty_table())
                if self.expected is not None and self.n_rows != self.expected:
                    raise ValueError(f"{self.path}: {self.n_rows} rows written, metadata says {self.expected}")
            self._writer.close()
        except BaseException:
            self._ctx.__exit__(*sys.exc_info())
            raise
        return self._ctx.__exit__(exc_type, exc, tb)


def write_tile_tables(tile_dir: str | Path, points_cols: dict | None, faces_cols: dict | None,
                      patches_cols: dict, meta: TileMeta, *, row_group_size: int = DEFAULT_ROW_GROUP_SIZE,
                      compression: str | dict = "auto") -> TileStoreSummary:
    """Write one tile's three tables (already sorted by patch, e.g. by ``tasks.partition.kernels.build_tile_tables``).

    Args:
        tile_dir: the tile folder (``WorkDir.tile_dir(tile)``); created if missing.
        points_cols / faces_cols: column name -> (n,) / (m,) arrays (see POINT_DTYPES / FACE_DTYPES);
            None or {} writes an empty table. Values are cast to the store dtypes (integers range-checked).
        patches_cols: column name -> (u,) arrays (PATCH_DTYPES); flags/label/score/bbox may be omitted.
        meta: tile key, patch size, CRS, texture list.
        row_group_size: rows per Parquet row group (the unit of selective reads).
        compression: "auto" (see module doc) or any pyarrow codec name / per-column dict.
    Raises:
        ValueError: unknown/missing columns, or patch ranges inconsistent with the data (nothing written).
    """
    t0 = time.perf_counter()
    tile_dir = Path(tile_dir)
    points = _complete(points_cols, "points", tile_dir)
    faces = _complete(faces_cols, "faces", tile_dir)
    patches = _complete(patches_cols, "patches", tile_dir)
    n_points, n_faces = len(points["x"]), len(faces["x0"])
    _check_ranges(patches, n_points, n_faces, points, faces, tile_dir)

    tile_dir.mkdir(parents=True, exist_ok=True)
    (tile_dir / PATCHES_FILE).unlink(missing_ok=True)  # the 'done' marker goes first and comes back last
    size = _write_table(tile_dir / POINTS_FILE, points, "points", meta.to_json("points", n_points),
                        row_group_size, compression)
    size += _write_table(tile_dir / FACES_FILE, faces, "faces", meta.to_json("faces", n_faces),
                         row_group_size, compression)
    size += _write_table(tile_dir / PATCHES_FILE, patches, "patches",
                         meta.to_json("patches", len(patches["patch"]), points_rows=n_points, faces_rows=n_faces),
                         row_group_size, compression)
    return TileStoreSummary(str(tile_dir), n_points, n_faces, len(patches["patch"]), size,
                            time.perf_counter() - t0)


def write_side_table(tile_dir: str | Path, name: str, cols: dict[str, np.ndarray], meta: TileMeta,
                     **extra_meta) -> Path:
    """Write a side table (labels / outliers / grades) of a tile, atomically.

    cols: column -> (u,) arrays of SIDE_TABLES[name]; ``patch`` must equal the patches table's column
    (checked against ``patches.parquet`` when it exists). extra_meta: JSON-able facts stored in the
    metadata (e.g. ``model_hash`` of the grades).
    """
    tile_dir = Path(tile_dir)
    path = side_table_path(tile_dir, name)
    dtypes = SIDE_TABLES[name]
    unknown = sorted(set(cols) - set(dtypes))
    missing = sorted(set(dtypes) - set(cols))
    if unknown or missing:
        raise ValueError(f"{path}: {name} needs columns {list(dtypes)} (unknown {unknown}, missing {missing})")
    out = {c: _cast(np.asarray(cols[c]), dt, f"{path}: {name}.{c}") for c, dt in dtypes.items()}
    if len({len(v) for v in out.values()}) > 1:
        raise ValueError(f"{path}: {name} columns differ in length")
    _write_table(path, out, name, meta.to_json(name, len(out["patch"])) | extra_meta, DEFAULT_ROW_GROUP_SIZE, "auto")
    return path
