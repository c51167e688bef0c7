"""The Parquet patch store (schema v2): one folder per tile, tables sorted by patch.

::

    tiles/{ix}_{iy}/points.parquet    MLS points, sorted by patch (one row per point)
    tiles/{ix}_{iy}/faces.parquet     mesh faces, 3 vertices inline, sorted by patch (one row per face)
    tiles/{ix}_{iy}/patches.parquet   one row per patch: ids, counts, row ranges, bbox
    tiles/{ix}_{iy}/labels.parquet    side table, one row per patch: ground-truth label (label stage)
    tiles/{ix}_{iy}/outliers.parquet  side table: count-outlier flags (outlier stage)
    tiles/{ix}_{iy}/grades.parquet    side table: score, grade (classify stage)

The partition output (points, faces, patches) is never rewritten by a later stage: labels, flags and
grades live in small side tables, aligned row for row with ``patches.parquet`` (same ``patch`` column;
a reader refuses a side table that does not match, so a stale one is never joined).

Coordinates are float32 metres, campus-local (offsets from the campus.json origin). ``patch`` is the
packed int64 key of :class:`storage.grid.PatchGrid` (world-anchored cells, so stable across runs and
campus extents); rows of patch p are ``point_start:point_stop`` / ``face_start:face_stop`` of the sorted
tables.

What v2 adds for the stages after partition:

- ``vid0, vid1, vid2`` (faces): a vertex id per corner, unique in the campus: ``source << 32 | vertex index``
  where ``source`` is the input file's stable id (:func:`storage.inputs.source_id`) and the index is the
  file's vertex index after welding exactly coincident vertices (seam-split glTF/PLY vertices get one
  id). Faces of a patch or a region weld exactly, and edge neighbours are exact (a shared vertex-id pair).
- ``vp0, vp1, vp2`` (faces): the patch holding each corner vertex (the paper's Algorithm 1, step 3).
- ``nx, ny, nz`` (faces): unit face normal (right hand on v0 -> v1 -> v2), computed in float64 world
  coordinates before the cast.
- ``source`` is the stable uint32 input id (points and faces), not a list position.
- Point normals are not stored: they cost a k-NN PCA over every point (the fusion stage needs them
  only in bad regions, a fraction of the campus, and computes them there).

Every file carries Parquet key-value metadata ``ms3d`` = JSON ``{"schema_version", "table", "units",
"frame", "patch_size_m", "tile", "crs", "n_rows"}`` (+ ``"textures"`` in faces, + ``"points_rows"``,
``"faces_rows"`` in patches so a reader can tell the three files belong together). Files are written to a
temporary name and renamed; ``patches.parquet`` is removed first and written last, so its presence marks
a complete tile. Stores of schema v1 are refused with a message saying to re-run.

Missing optional input columns are written with documented defaults (:data:`POINT_DEFAULTS`,
:data:`FACE_DEFAULTS`): zeros for attributes, NaN for uv and normals, -1 for ``texture``, ``src_face``
and vertex ids. Unknown columns are rejected: the schema is fixed per ``schema_version``.

Compression ("auto"): coordinates, uv and gps_time are stored uncompressed (float32 mantissas of metre
offsets are close to random: lz4/zstd gain ~10 % and halve write speed); patch, source, texture and
classification are dictionary + RLE encoded; other integer attributes use lz4. Measured on 5 M MLS-like
points: ~0.7 s CPU to write, 163 MB; zstd everywhere 1.3 s, 113 MB. Pass ``compression="zstd"`` for
archival size.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .atomic import atomic_path
from .columns import arrow_array
from .errors import InputError

SCHEMA_VERSION = 2
META_KEY = b"ms3d"
FRAME = "campus-local float32 offsets from campus.json origin"
DEFAULT_ROW_GROUP_SIZE = 65536

POINTS_FILE, FACES_FILE, PATCHES_FILE = "points.parquet", "faces.parquet", "patches.parquet"

_F32, _F64 = np.dtype(np.float32), np.dtype(np.float64)

POINT_DTYPES: dict[str, np.dtype] = {
    "x": _F32, "y": _F32, "z": _F32,
    "intensity": np.dtype(np.uint16),
    "gps_time": _F64,
    "red": np.dtype(np.uint16), "green": np.dtype(np.uint16), "blue": np.dtype(np.uint16),
    "classification": np.dtype(np.uint8),
    "source": np.dtype(np.uint32),
    "patch": np.dtype(np.int64),
}
POINT_DEFAULTS = {"intensity": 0, "gps_time": 0.0, "red": 0, "green": 0, "blue": 0, "classification": 0, "source": 0}

FACE_DTYPES: dict[str, np.dtype] = {
    **{f"{a}{v}": _F32 for v in range(3) for a in "xyz"},
    **{f"vid{v}": np.dtype(np.int64) for v in range(3)},
    **{f"vp{v}": np.dtype(np.int64) for v in range(3)},
    "nx": _F32, "ny": _F32, "nz": _F32,
    **{f"{a}{v}": _F32 for v in range(3) for a in "uv"},
    "texture": np.dtype(np.int16),
    "red": np.dtype(np.uint8), "green": np.dtype(np.uint8), "blue": np.dtype(np.uint8),
    "src_face": np.dtype(np.int64),
    "source": np.dtype(np.uint32),
    "patch": np.dtype(np.int64),
}
FACE_DEFAULTS = {**{f"{a}{v}": np.nan for v in range(3) for a in "uv"},
                 **{f"vid{v}": -1 for v in range(3)}, **{f"vp{v}": -1 for v in range(3)},
                 "nx": np.nan, "ny": np.nan, "nz": np.nan,
                 "texture": -1, "red": 0, "green": 0, "blue": 0, "src_face": -1, "source": 0}

PATCH_DTYPES: dict[str, np.dtype] = {
    "patch": np.dtype(np.int64),
    "i": np.dtype(np.int64), "j": np.dtype(np.int64), "k": np.dtype(np.int64),
    "n_points": np.dtype(np.int32), "n_faces": np.dtype(np.int32),
    "point_start": np.dtype(np.int64), "point_stop": np.dtype(np.int64),
    "face_start": np.dtype(np.int64), "face_stop": np.dtype(np.int64),
    **{c: _F32 for c in ("xmin", "ymin", "zmin", "xmax", "ymax", "zmax")},
}
PATCH_DEFAULTS = {c: np.nan for c in ("xmin", "ymin", "zmin", "xmax", "ymax", "zmax")}

# Side tables: one row per patch of patches.parquet, same order, written by later stages.
SIDE_TABLES: dict[str, dict[str, np.dtype]] = {
    "labels": {"patch": np.dtype(np.int64), "label": np.dtype(np.int8)},  # -1 unknown, 0 good, 1 bad
    "outliers": {"patch": np.dtype(np.int64), "outlier_points": np.dtype(bool),
                 "outlier_faces": np.dtype(bool), "outlier": np.dtype(bool)},
    "grades": {"patch": np.dtype(np.int64), "score": _F32, "grade": np.dtype(np.int8)},  # grade -1 unknown
}

_TABLES = {"points": (POINTS_FILE, POINT_DTYPES, POINT_DEFAULTS),
           "faces": (FACES_FILE, FACE_DTYPES, FACE_DEFAULTS),
           "patches": (PATCHES_FILE, PATCH_DTYPES, PATCH_DEFAULTS)}
# Dictionary + RLE for the sorted keys only (measured on 7.6 M points: 0.72 s against 1.05 s with source /
# texture / classification too, same size: lz4 packs those just as well).
_DICT_COLUMNS = ["patch", "vp0", "vp1", "vp2"]
_RAW_COLUMNS = {"x", "y", "z", "gps_time", "nx", "ny", "nz", *_DICT_COLUMNS} | {
    f"{a}{v}" for v in range(3) for a in "xyzuv"}


def _arrow_schema(dtypes: dict[str, np.dtype]) -> pa.Schema:
    return pa.schema([pa.field(name, pa.from_numpy_dtype(dt), nullable=False) for name, dt in dtypes.items()])


SCHEMAS = {name: _arrow_schema(spec[1]) for name, spec in _TABLES.items()} | {
    name: _arrow_schema(dtypes) for name, dtypes in SIDE_TABLES.items()}


@dataclass(frozen=True)
class TileMeta:
    """What a tile's files say about themselves.

    tile: TileId key "ix_iy"; patch_size_m: (3,) metres; crs: e.g. "EPSG:32650" or None;
    textures: texture image paths, indexed by the faces' ``texture`` column.
    """

    tile: str
    patch_size_m: tuple[float, float, float]
    crs: str | None = None
    textures: tuple[str, ...] = ()

    def to_json(self, table: str, n_rows: int, **extra) -> dict:
        d = {"schema_version": SCHEMA_VERSION, "table": table, "units": "metre", "frame": FRAME,
             "patch_size_m": [float(v) for v in self.patch_size_m], "tile": self.tile, "crs": self.crs,
             "n_rows": int(n_rows)}
        if table == "faces":
            d["textures"] = list(self.textures)
        return d | extra


@dataclass(frozen=True)
class TileStoreSummary:
    tile_dir: str
    n_points: int
    n_faces: int
    n_patches: int
    bytes_written: int
    seconds: float


# ----------------------------------------------------------------------------------------------- write

def _complete(cols: dict | None, table: str, where: Path) -> dict[str, np.ndarray]:
    """Columns in schema order and dtypes, defaults filled in. Raises ValueError for bad columns."""
    _, dtypes, defaults = _TABLES[table]
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
    return {name: ("none" if name in _RAW_COLUMNS else "lz4") for name in _TABLES[table][1]} \
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
        self._dictionary = [c for c in _DICT_COLUMNS if c in _TABLES[table][1]] if table in ("points", "faces") else True

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


# ------------------------------------------------------------------------------------------------ read

def _open(path: Path, table: str) -> tuple[pq.ParquetFile, dict]:
    """Open and validate one store file; every failure is an InputError naming the file."""
    if not path.exists():
        raise InputError(path, f"missing ({table} table of the patch store)")
    try:
        pf = pq.ParquetFile(path)
        schema = pf.schema_arrow
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise InputError(path, f"not a readable Parquet file ({exc})") from None
    raw = (schema.metadata or {}).get(META_KEY)
    if raw is None:
        raise InputError(path, "no 'ms3d' metadata: not written by the ms3d patch store")
    try:
        meta = json.loads(raw)
    except ValueError:
        raise InputError(path, "the 'ms3d' metadata is not valid JSON") from None
    if meta.get("schema_version") != SCHEMA_VERSION:
        raise InputError(path, f"patch store schema_version {meta.get('schema_version')!r}; this ms3d reads only "
                               f"v{SCHEMA_VERSION} (vertex ids, world-anchored patch ids): re-run `ms3d run` on the "
                               "work dir to rebuild the stores")
    if meta.get("table") != table:
        raise InputError(path, f"holds table {meta.get('table')!r}, expected {table!r}")
    expected = SCHEMAS[table]
    for f in expected:
        i = schema.get_field_index(f.name)
        if i < 0 or schema.field(i).type != f.type:
            got = "missing" if i < 0 else str(schema.field(i).type)
            raise InputError(path, f"column {f.name!r} should be {f.type}, is {got}")
    if pf.metadata.num_rows != meta.get("n_rows"):
        raise InputError(path, f"{pf.metadata.num_rows} rows, metadata says {meta.get('n_rows')}")
    return pf, meta


def _to_numpy(t: pa.Table, columns, dtypes: dict) -> dict[str, np.ndarray]:
    out = {}
    for name in columns:
        col = t.column(name)
        out[name] = col.to_numpy() if col.num_chunks else np.zeros(0, dtype=dtypes[name])
    return out


def side_table_path(tile_dir: str | Path, name: str) -> Path:
    if name not in SIDE_TABLES:
        raise ValueError(f"unknown side table {name!r}; known: {list(SIDE_TABLES)}")
    return Path(tile_dir) / f"{name}.parquet"


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


def read_side_table(tile_dir: str | Path, name: str, patch_keys: np.ndarray | None = None) -> tuple[dict, dict] | None:
    """A tile's side table as (columns, metadata), or None when it was never written.

    patch_keys: the patches table's ``patch`` column; a side table whose keys differ is stale (written
    for an older partition) and raises InputError rather than being joined to the wrong patches.
    """
    path = side_table_path(tile_dir, name)
    if not path.exists():
        return None
    pf, meta = _open(path, name)
    try:
        cols = _to_numpy(pf.read(), SIDE_TABLES[name], SIDE_TABLES[name])
    except (OSError, pa.ArrowException) as exc:
        raise InputError(path, f"cannot read ({exc})") from None
    if patch_keys is not None and not np.array_equal(cols["patch"], patch_keys):
        raise InputError(path, f"{name} do not match the tile's patches (stale): re-run `ms3d run`")
    return cols, meta


from .patch_reader import PatchData, PatchStore, StoreStats  # noqa: F401 - re-exported; the reader builds on the above
