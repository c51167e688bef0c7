"""Small Parquet helpers for column dicts (staging files between ingest and partition)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .atomic import atomic_path
from .errors import InputError


def write_columns(path: str | Path, cols: dict[str, np.ndarray], meta: dict | None = None,
                  compression: str = "lz4") -> Path:
    """Write equal-length 1-D numpy columns as one Parquet file, atomically; ``meta`` is stored as
    JSON under the ``ms3d`` key of the schema metadata."""
    table = pa.table({k: pa.array(np.ascontiguousarray(v)) for k, v in cols.items()})
    if meta is not None:
        table = table.replace_schema_metadata({"ms3d": json.dumps(meta)})
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, compression=compression)
    return Path(path)


def read_columns(path: str | Path) -> tuple[dict[str, np.ndarray], dict]:
    """Inverse of write_columns: (columns, meta)."""
    try:
        table = pq.read_table(path)
    except (OSError, pa.ArrowInvalid) as e:
        raise InputError(path, f"unreadable Parquet file ({e})") from None
    raw = (table.schema.metadata or {}).get(b"ms3d")
    meta = json.loads(raw) if raw else {}
    return {name: table.column(name).to_numpy() for name in table.column_names}, meta


# --------------------------------------------------------------------------------- sorted runs

RUN_ROW_GROUP = 32_768  # rows per row group of a staging run: the unit of partial reads when merging
_RUN_DICT_COLUMNS = ("source", "texture", "classification")  # few distinct values: dictionary + RLE


def write_run(path: str | Path, cols: dict[str, np.ndarray], meta: dict | None = None) -> Path:
    """Write a *sorted run*: equal-length columns already sorted by their int64 ``patch`` column, as
    Parquet with row groups of :data:`RUN_ROW_GROUP` rows and min/max statistics on ``patch`` only, so a
    merge can read just the row groups of a key range (:func:`run_row_groups`). Float columns are
    stored raw (float32 offsets are incompressible), integers with lz4. Atomic; ``meta`` as in
    :func:`write_columns`."""
    keys = np.asarray(cols["patch"])
    if len(keys) > 1 and (keys[1:] < keys[:-1]).any():
        raise ValueError(f"{path}: a run must be sorted by patch")
    table = pa.table({k: pa.array(np.ascontiguousarray(v)) for k, v in cols.items()})
    if meta is not None:
        table = table.replace_schema_metadata({"ms3d": json.dumps(meta)})
    compression = {k: ("none" if np.asarray(v).dtype.kind == "f" else "lz4") for k, v in cols.items()}
    with atomic_path(path) as tmp:
        pq.write_table(table, tmp, row_group_size=RUN_ROW_GROUP, compression=compression,
                       use_dictionary=[c for c in _RUN_DICT_COLUMNS if c in cols], write_statistics=["patch"])
    return Path(path)


def run_row_groups(pf: pq.ParquetFile) -> np.ndarray:
    """(g, 3) int64 rows of (min patch key, max patch key, rows) of each row group of a sorted run."""
    md = pf.metadata
    col = pf.schema_arrow.get_field_index("patch")
    out = np.zeros((md.num_row_groups, 3), dtype=np.int64)
    for g in range(md.num_row_groups):
        rg = md.row_group(g)
        st = rg.column(col).statistics
        out[g] = (st.min, st.max, rg.num_rows)
    return out


def read_meta(path: str | Path) -> dict:
    """The ``ms3d`` metadata of a Parquet file written by :func:`write_columns` / :func:`write_run`."""
    try:
        raw = (pq.read_schema(path).metadata or {}).get(b"ms3d")
    except (OSError, pa.ArrowInvalid) as e:
        raise InputError(path, f"unreadable Parquet file ({e})") from None
    return json.loads(raw) if raw else {}
