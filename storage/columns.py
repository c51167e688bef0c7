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
