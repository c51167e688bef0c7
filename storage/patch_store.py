"""The Parquet patch store: one folder per tile, three tables sorted by patch.

::

    tiles/{ix}_{iy}/points.parquet    MLS points, sorted by patch (one row per point)
    tiles/{ix}_{iy}/faces.parquet     mesh faces, 3 vertices inline, sorted by patch (one row per face)
    tiles/{ix}_{iy}/patches.parquet   one row per patch: ids, counts, row ranges, bbox, flags, label, score

Coordinates are float32 metres, campus-local (offsets from the campus.json origin). ``patch`` is the
packed int64 key of ``tasks.partition.pack_patch_key`` (three biased 21-bit fields, i highest); rows of
patch p are ``point_start:point_stop`` / ``face_start:face_stop`` of the sorted tables.

Every file carries Parquet key-value metadata ``ms3d`` = JSON ``{"schema_version", "table", "units",
"frame", "patch_size_m", "tile", "crs", "n_rows"}`` (+ ``"textures"`` in faces, + ``"points_rows"``,
``"faces_rows"`` in patches so a reader can tell the three files belong together). Files are written to a
temporary name and renamed; ``patches.parquet`` is removed first and written last, so its presence marks
a complete tile.

Missing optional input columns are written with documented defaults (:data:`POINT_DEFAULTS`,
:data:`FACE_DEFAULTS`): zeros for attributes, NaN for uv, -1 for ``texture`` and ``src_face``. Unknown
columns are rejected: the schema is fixed per ``schema_version``.

Compression ("auto"): coordinates, uv and gps_time are stored uncompressed (float32 mantissas of metre
offsets are close to random: lz4/zstd gain ~10 % and halve write speed); patch, source, texture and
classification are dictionary + RLE encoded; other integer attributes use lz4. Measured on 5 M MLS-like
points: ~0.7 s CPU to write, 163 MB; zstd everywhere 1.3 s, 113 MB. Pass ``compression="zstd"`` for
archival size.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .atomic import atomic_path
from .errors import InputError
from .ids import PatchId

SCHEMA_VERSION = 1
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
    "source": np.dtype(np.uint16),
    "patch": np.dtype(np.int64),
}
POINT_DEFAULTS = {"intensity": 0, "gps_time": 0.0, "red": 0, "green": 0, "blue": 0, "classification": 0, "source": 0}

FACE_DTYPES: dict[str, np.dtype] = {
    **{f"{a}{v}": _F32 for v in range(3) for a in "xyz"},
    **{f"{a}{v}": _F32 for v in range(3) for a in "uv"},
    "texture": np.dtype(np.int16),
    "red": np.dtype(np.uint8), "green": np.dtype(np.uint8), "blue": np.dtype(np.uint8),
    "src_face": np.dtype(np.int64),
    "source": np.dtype(np.uint16),
    "patch": np.dtype(np.int64),
}
FACE_DEFAULTS = {**{f"{a}{v}": np.nan for v in range(3) for a in "uv"},
                 "texture": -1, "red": 0, "green": 0, "blue": 0, "src_face": -1, "source": 0}

PATCH_DTYPES: dict[str, np.dtype] = {
    "patch": np.dtype(np.int64),
    "i": np.dtype(np.int32), "j": np.dtype(np.int32), "k": np.dtype(np.int32),
    "n_points": np.dtype(np.int32), "n_faces": np.dtype(np.int32),
    "point_start": np.dtype(np.int64), "point_stop": np.dtype(np.int64),
    "face_start": np.dtype(np.int64), "face_stop": np.dtype(np.int64),
    **{c: _F32 for c in ("xmin", "ymin", "zmin", "xmax", "ymax", "zmax")},
    "outlier_points": np.dtype(bool), "outlier_faces": np.dtype(bool), "outlier": np.dtype(bool),
    "label": np.dtype(np.int8),
    "score": _F32,
}
PATCH_DEFAULTS = {**{c: np.nan for c in ("xmin", "ymin", "zmin", "xmax", "ymax", "zmax")},
                  "outlier_points": False, "outlier_faces": False, "outlier": False, "label": -1, "score": np.nan}
UPDATABLE_PATCH_COLUMNS = ("outlier_points", "outlier_faces", "outlier", "label", "score")

_TABLES = {"points": (POINTS_FILE, POINT_DTYPES, POINT_DEFAULTS),
           "faces": (FACES_FILE, FACE_DTYPES, FACE_DEFAULTS),
           "patches": (PATCHES_FILE, PATCH_DTYPES, PATCH_DEFAULTS)}
_DICT_COLUMNS = ["patch", "source", "texture", "classification"]  # few distinct values: dictionary + RLE
_RAW_COLUMNS = {"x", "y", "z", "gps_time", *_DICT_COLUMNS} | {f"{a}{v}" for v in range(3) for a in "xyzuv"}


def _arrow_schema(dtypes: dict[str, np.dtype]) -> pa.Schema:
    return pa.schema([pa.field(name, pa.from_numpy_dtype(dt), nullable=False) for name, dt in dtypes.items()])


SCHEMAS = {name: _arrow_schema(spec[1]) for name, spec in _TABLES.items()}


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


@dataclass
class StoreStats:
    """Counters of what a :class:`PatchStore` has read (tests use them to prove selective reads)."""

    row_groups_read: int = 0
    points_row_groups_read: int = 0
    faces_row_groups_read: int = 0
    rows_read: int = 0


@dataclass(frozen=True)
class PatchData:
    """One patch's content. points/faces: column name -> (n,) / (m,) arrays in store dtypes."""

    key: int
    ijk: tuple[int, int, int]
    points: dict[str, np.ndarray] = field(repr=False)
    faces: dict[str, np.ndarray] = field(repr=False)

    @property
    def n_points(self) -> int:
        return len(next(iter(self.points.values()))) if self.points else 0

    @property
    def n_faces(self) -> int:
        return len(next(iter(self.faces.values()))) if self.faces else 0

    def xyz(self) -> np.ndarray:
        """(n, 3) float32 point coordinates, metres, campus-local."""
        return np.stack([self.points[c] for c in "xyz"], axis=1)

    def triangles(self) -> np.ndarray:
        """(m, 3, 3) float32 face vertices, metres, campus-local."""
        return np.stack([np.stack([self.faces[f"{a}{v}"] for a in "xyz"], axis=1) for v in range(3)], axis=1)

    def __repr__(self) -> str:
        return f"PatchData(key={self.key}, ijk={self.ijk}, n_points={self.n_points}, n_faces={self.n_faces})"


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
        if table != "patches" else "zstd"


def _write_table(path: Path, cols: dict, table: str, meta_json: dict, row_group_size: int, compression) -> int:
    schema = SCHEMAS[table].with_metadata({META_KEY: json.dumps(meta_json).encode()})
    t = pa.Table.from_arrays([pa.array(cols[f.name], type=f.type) for f in schema], schema=schema)
    with atomic_path(path) as tmp:
        pq.write_table(
            t, tmp, row_group_size=row_group_size, compression=_compression(table, compression),
            use_dictionary=[c for c in _DICT_COLUMNS if c in cols] if table != "patches" else True,
            sorting_columns=[pq.SortingColumn(schema.get_field_index("patch"))],
        )
    return path.stat().st_size


def write_tile_tables(tile_dir: str | Path, points_cols: dict | None, faces_cols: dict | None,
                      patches_cols: dict, meta: TileMeta, *, row_group_size: int = DEFAULT_ROW_GROUP_SIZE,
                      compression: str | dict = "auto") -> TileStoreSummary:
    """Write one tile's three tables (already sorted by patch, e.g. by ``tasks.partition.build_tile_tables``).

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
        raise InputError(path, f"schema_version {meta.get('schema_version')!r}, this ms3d reads {SCHEMA_VERSION}: "
                               "re-run the partition stage")
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


def _n_rows(cols: dict) -> int:
    return len(next(iter(cols.values()))) if cols else 0


def _find_sorted(hay: np.ndarray, needles: np.ndarray, what: str, shown=None) -> np.ndarray:
    """Positions of needles in the sorted unique ``hay``; KeyError listing (up to 5) missing ones."""
    pos = np.searchsorted(hay, needles)
    found = pos < len(hay)
    found[found] = hay[pos[found]] == needles[found]
    if not found.all():
        shown = needles if shown is None else shown
        raise KeyError(f"{what}: {shown[~found][:5].tolist()}")
    return pos


class _RowGroupFile:
    """A data table (points or faces) read by row groups."""

    def __init__(self, pf: pq.ParquetFile, path: Path, dtypes: dict):
        self.pf, self.path, self.dtypes = pf, path, dtypes
        md = pf.metadata
        sizes = np.array([md.row_group(g).num_rows for g in range(md.num_row_groups)], dtype=np.int64)
        self.bounds = np.concatenate(([0], np.cumsum(sizes)))  # row group g holds rows bounds[g]:bounds[g+1]

    def read(self, ranges: np.ndarray, columns) -> tuple[dict, np.ndarray, int]:
        """ranges: (r, 2) int64 [start, stop) rows. Returns (columns of the concatenated row groups that
        overlap any non-empty range, (r,) int64 start of each range in them, row groups read)."""
        columns = list(self.dtypes) if columns is None else list(columns)
        start, stop = ranges[:, 0], ranges[:, 1]
        filled = stop > start
        n_groups = len(self.bounds) - 1
        g0 = np.searchsorted(self.bounds, start[filled], side="right") - 1
        g1 = np.searchsorted(self.bounds, stop[filled] - 1, side="right") - 1
        mark = np.zeros(n_groups + 1, dtype=np.int64)
        np.add.at(mark, g0, 1)
        np.add.at(mark, g1 + 1, -1)
        need = np.flatnonzero(np.cumsum(mark)[:-1] > 0)
        if len(need):
            try:
                t = self.pf.read_row_groups(need.tolist(), columns=columns)
            except (OSError, pa.ArrowException) as exc:
                raise InputError(self.path, f"cannot read row groups ({exc})") from None
            data = _to_numpy(t, columns, self.dtypes)
        else:
            data = {c: np.zeros(0, dtype=self.dtypes[c]) for c in columns}
        # where each needed row group begins in the concatenation; overlapped groups are consecutive there
        sizes = np.diff(self.bounds)[need]
        at = np.full(n_groups, -1, dtype=np.int64)
        at[need] = np.cumsum(sizes) - sizes
        local = np.zeros(len(ranges), dtype=np.int64)
        local[filled] = start[filled] - self.bounds[g0] + at[g0]
        return data, local, len(need)


class PatchStore:
    """Reader of one tile folder.

    >>> store = PatchStore(work.tile_dir(TileId(0, 0)))        # doctest: +SKIP
    >>> store.read_patch(PatchId(2, 2, 1)).xyz().shape           # doctest: +SKIP
    (1532, 3)

    Raises InputError (naming the file) for a missing or corrupt file, a schema_version mismatch, or files
    that do not belong together.
    """

    def __init__(self, tile_dir: str | Path):
        self.tile_dir = Path(tile_dir)
        self.stats = StoreStats()
        pf, pmeta = _open(self.tile_dir / PATCHES_FILE, "patches")
        try:
            table = pf.read()
        except (OSError, pa.ArrowException) as exc:
            raise InputError(self.tile_dir / PATCHES_FILE, f"cannot read ({exc})") from None
        self._patches = _to_numpy(table, PATCH_DTYPES, PATCH_DTYPES)
        files = {}
        for table_name, file_name, rows_key in (("points", POINTS_FILE, "points_rows"),
                                                ("faces", FACES_FILE, "faces_rows")):
            path = self.tile_dir / file_name
            f, m = _open(path, table_name)
            if m["n_rows"] != pmeta.get(rows_key) or m["tile"] != pmeta["tile"] \
                    or m["patch_size_m"] != pmeta["patch_size_m"]:
                raise InputError(path, f"does not belong with {PATCHES_FILE} (rows/tile/patch size differ): "
                                       "the tile was partly rewritten; re-run the partition stage")
            files[table_name] = (f, m)
        self._points = _RowGroupFile(files["points"][0], self.tile_dir / POINTS_FILE, POINT_DTYPES)
        self._faces = _RowGroupFile(files["faces"][0], self.tile_dir / FACES_FILE, FACE_DTYPES)
        self.meta = TileMeta(tile=pmeta["tile"], patch_size_m=tuple(pmeta["patch_size_m"]), crs=pmeta.get("crs"),
                             textures=tuple(files["faces"][1].get("textures", ())))

    def __repr__(self) -> str:
        return f"PatchStore({str(self.tile_dir)!r}, n_patches={len(self._patches['patch'])})"

    def patches(self) -> dict[str, np.ndarray]:
        """The patches table: column name -> (u,) array (PATCH_DTYPES), rows ascending by ``patch``."""
        return dict(self._patches)

    @property
    def n_points(self) -> int:
        return int(self._points.bounds[-1])

    @property
    def n_faces(self) -> int:
        return int(self._faces.bounds[-1])

    def _rows_of(self, keys) -> np.ndarray:
        """Patch keys (ints) or PatchIds -> (r,) row indices into the patches table; KeyError if absent."""
        p = self._patches
        keys = list(keys)
        is_id = np.array([isinstance(k, PatchId) for k in keys], dtype=bool)
        rows = np.empty(len(keys), dtype=np.int64)
        if (~is_id).any():
            want = np.array([k for k, m in zip(keys, is_id) if not m], dtype=np.int64)
            rows[~is_id] = _find_sorted(p["patch"], want, f"patch keys not in tile {self.meta.tile}")
        if is_id.any():
            # Rows ascend by key, i.e. by (i, j, k): a mixed-radix rank of (i, j, k) over the table and the
            # query is ascending too, so PatchIds are found without re-implementing the key packing here.
            q = np.array([(k.i, k.j, k.k) for k, m in zip(keys, is_id) if m], dtype=np.int64)
            t = np.stack([p["i"], p["j"], p["k"]], axis=1).astype(np.int64)
            both = np.concatenate((t, q))
            lo, ext = both.min(axis=0), both.max(axis=0) - both.min(axis=0) + 1

            def rank(a):
                return ((a[:, 0] - lo[0]) * ext[1] + (a[:, 1] - lo[1])) * ext[2] + (a[:, 2] - lo[2])

            rows[is_id] = _find_sorted(rank(t), rank(q), f"patches (i, j, k) not in tile {self.meta.tile}",
                                       shown=q)
        return rows

    def read_patches(self, keys, point_columns=None, face_columns=None) -> list[PatchData]:
        """Read several patches, touching only the row groups that overlap their row ranges.

        Args:
            keys: iterable of packed int keys and/or PatchId.
            point_columns / face_columns: subsets of columns to read (default: all).
        Returns:
            one PatchData per key, in the order given (arrays are views into one read buffer).
        """
        rows = self._rows_of(keys)
        p = self._patches
        pr = np.stack([p["point_start"][rows], p["point_stop"][rows]], axis=1)
        fr = np.stack([p["face_start"][rows], p["face_stop"][rows]], axis=1)
        pdata, plocal, pgroups = self._points.read(pr, point_columns)
        fdata, flocal, fgroups = self._faces.read(fr, face_columns)
        self.stats.points_row_groups_read += pgroups
        self.stats.faces_row_groups_read += fgroups
        self.stats.row_groups_read += pgroups + fgroups
        self.stats.rows_read += _n_rows(pdata) + _n_rows(fdata)
        out = []
        for r, (row, ps, fs) in enumerate(zip(rows, plocal, flocal)):  # one small dict of views per patch
            pn, fn = pr[r, 1] - pr[r, 0], fr[r, 1] - fr[r, 0]
            out.append(PatchData(
                key=int(p["patch"][row]), ijk=(int(p["i"][row]), int(p["j"][row]), int(p["k"][row])),
                points={c: v[ps:ps + pn] for c, v in pdata.items()},
                faces={c: v[fs:fs + fn] for c, v in fdata.items()},
            ))
        return out

    def read_patch(self, key, point_columns=None, face_columns=None) -> PatchData:
        """One patch by packed key or PatchId (KeyError if the tile has no such patch)."""
        return self.read_patches([key], point_columns, face_columns)[0]

    def read_all(self, point_columns=None, face_columns=None) -> tuple[dict, dict]:
        """The whole points and faces tables as column dicts (sorted by patch)."""
        all_p = np.array([[0, self.n_points]], dtype=np.int64)
        all_f = np.array([[0, self.n_faces]], dtype=np.int64)
        pdata, _, pg = self._points.read(all_p, point_columns)
        fdata, _, fg = self._faces.read(all_f, face_columns)
        self.stats.points_row_groups_read += pg
        self.stats.faces_row_groups_read += fg
        self.stats.row_groups_read += pg + fg
        return pdata, fdata


def update_patch_columns(tile_dir: str | Path, updates: dict[str, np.ndarray]) -> None:
    """Replace flag/label/score columns of ``patches.parquet`` (rewritten atomically, metadata kept).

    updates: column -> (u,) array, u = rows of the patches table; columns among UPDATABLE_PATCH_COLUMNS.
    """
    path = Path(tile_dir) / PATCHES_FILE
    pf, meta = _open(path, "patches")
    bad = sorted(set(updates) - set(UPDATABLE_PATCH_COLUMNS))
    if bad:
        raise ValueError(f"{path}: cannot update {bad}; updatable: {list(UPDATABLE_PATCH_COLUMNS)}")
    try:
        table = pf.read()
    except (OSError, pa.ArrowException) as exc:
        raise InputError(path, f"cannot read ({exc})") from None
    cols = _to_numpy(table, PATCH_DTYPES, PATCH_DTYPES)
    for name, values in updates.items():
        v = _cast(np.asarray(values), PATCH_DTYPES[name], f"{path}: patches.{name}")
        if len(v) != len(cols["patch"]):
            raise ValueError(f"{path}: {name} has {len(v)} values for {len(cols['patch'])} patches")
        cols[name] = v
    _write_table(path, cols, "patches", meta, DEFAULT_ROW_GROUP_SIZE, "auto")
