"""Reading the Parquet patch store (contract in :mod:`storage.patches`).

One tile folder is opened as a :class:`PatchStore`: the patches table is read whole (it is small), the
points and faces tables by row groups, so reading one patch touches only the row groups its rows lie in.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from storage import recorded
from storage.errors import InputError
from storage.grid import PatchGrid
from storage.ids import PatchId
from storage.patches.schema import (
    FACE_DTYPES,
    FACES_FILE,
    PATCH_DTYPES,
    PATCHES_FILE,
    POINT_DTYPES,
    POINTS_FILE,
    SIDE_TABLES,
    TileMeta,
    open_table,
    side_table_path,
    table_columns,
)


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

    def vertex_ids(self) -> np.ndarray:
        """(m, 3) int64 campus-unique vertex id of each face corner."""
        return np.stack([self.faces[f"vid{v}"] for v in range(3)], axis=1)

    def normals(self) -> np.ndarray:
        """(m, 3) float32 unit face normals."""
        return np.stack([self.faces[c] for c in ("nx", "ny", "nz")], axis=1)

    def __repr__(self) -> str:
        return f"PatchData(key={self.key}, ijk={self.ijk}, n_points={self.n_points}, n_faces={self.n_faces})"


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
            data = table_columns(t, columns, self.dtypes)
        else:
            data = {c: np.zeros(0, dtype=self.dtypes[c]) for c in columns}
        # where each needed row group begins in the concatenation; overlapped groups are consecutive there
        sizes = np.diff(self.bounds)[need]
        at = np.full(n_groups, -1, dtype=np.int64)
        at[need] = np.cumsum(sizes) - sizes
        local = np.zeros(len(ranges), dtype=np.int64)
        local[filled] = start[filled] - self.bounds[g0] + at[g0]
        return data, local, len(need)

    def read_stacked(self, columns, dtype) -> tuple[np.ndarray, int]:
        """Every row of ``columns`` as one (n_rows, len(columns)) ``dtype`` array, filled one row group at
        a time (the peak is the result plus one row group, not the whole table twice). Returns (array,
        row groups read)."""
        columns = list(columns)
        out = np.empty((int(self.bounds[-1]), len(columns)), dtype)
        for g in range(len(self.bounds) - 1):
            try:
                t = self.pf.read_row_group(g, columns=columns)
            except (OSError, pa.ArrowException) as exc:
                raise InputError(self.path, f"cannot read row group {g} ({exc})") from None
            lo, hi = self.bounds[g], self.bounds[g + 1]
            for j, c in enumerate(columns):
                out[lo:hi, j] = t.column(c).to_numpy()
            del t
        return out, len(self.bounds) - 1


class PatchStore:
    """Reader of one tile folder.

    >>> store = PatchStore(work.tile_dir(TileId(0, 0)))        # doctest: +SKIP
    >>> store.read_patch(PatchId(2, 2, 1)).xyz().shape           # doctest: +SKIP
    (1532, 3)

    Raises InputError (naming the file) for a missing or corrupt file, a schema_version mismatch, or files
    that do not belong together.
    """

    def __init__(self, tile_dir: str | Path, sources: dict | None = None):
        """sources: {file name: seekable file object} to read the points or faces table from instead of the
        tile folder (:func:`storage.patches.remote_read.open_for_patches`: byte ranges of a bucket's object)."""
        self.tile_dir = Path(tile_dir)
        self.stats = StoreStats()
        sources = sources or {}
        recorded.ensure_local(*(self.tile_dir / n for n in (PATCHES_FILE, POINTS_FILE, FACES_FILE) if n not in sources))
        table, pmeta = _patches_table(self.tile_dir)
        self._patches = table_columns(table, PATCH_DTYPES, PATCH_DTYPES)
        files = {}
        for table_name, file_name, rows_key in (("points", POINTS_FILE, "points_rows"),
                                                ("faces", FACES_FILE, "faces_rows")):
            path = self.tile_dir / file_name
            f, m = open_table(path, table_name, sources.get(file_name))
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

    def side(self, name: str) -> dict[str, np.ndarray] | None:
        """A side table ("labels", "outliers", "grades") aligned row for row with :meth:`patches`, or
        None when the stage that writes it has not run. Raises InputError for a stale one."""
        got = read_side_table(self.tile_dir, name, self._patches["patch"])
        return None if got is None else got[0]

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
            q = np.array([(k.i, k.j, k.k) for k, m in zip(keys, is_id) if m], dtype=np.int64)
            rows[is_id] = _find_sorted(p["patch"], PatchGrid.pack(q), f"patches (i, j, k) not in tile {self.meta.tile}",
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

    def read_all_stacked(self, table: str, columns, dtype=np.float32) -> np.ndarray:
        """The whole ``table`` ("points" or "faces") as one (n, len(columns)) ``dtype`` array, rows sorted by
        patch: ``read_all`` without its column copies, for whole-tile readers that stack columns anyway."""
        rg = {"points": self._points, "faces": self._faces}[table]
        out, groups = rg.read_stacked(columns, dtype)
        setattr(self.stats, f"{table}_row_groups_read", getattr(self.stats, f"{table}_row_groups_read") + groups)
        self.stats.row_groups_read += groups
        return out


    def read_rows_stacked(self, table: str, columns, lo: int, hi: int, dtype=np.float32) -> np.ndarray:
        """Rows ``lo:hi`` of ``table`` ("points" or "faces") as one (hi - lo, len(columns)) ``dtype`` array,
        reading only the row groups that hold them: a whole-tile reader's bounded window."""
        rg = {"points": self._points, "faces": self._faces}[table]
        columns = list(columns)
        out = np.empty((max(int(hi) - int(lo), 0), len(columns)), dtype)
        if len(out) == 0:
            return out
        data, local, groups = rg.read(np.array([[lo, hi]], np.int64), columns)
        at = int(local[0])
        for j, c in enumerate(columns):
            out[:, j] = data[c][at:at + len(out)]
        del data
        setattr(self.stats, f"{table}_row_groups_read", getattr(self.stats, f"{table}_row_groups_read") + groups)
        self.stats.row_groups_read += groups
        return out


def _patches_table(tile_dir: Path) -> tuple[pa.Table, dict]:
    pf, pmeta = open_table(tile_dir / PATCHES_FILE, "patches")
    try:
        return pf.read(), pmeta
    except (OSError, pa.ArrowException) as exc:
        raise InputError(tile_dir / PATCHES_FILE, f"cannot read ({exc})") from None


class PatchTable:
    """A tile's patches table and side tables without its points and faces (a census, a count): on a work dir
    on a bucket only these small files are downloaded. ``patches()`` and ``side(name)`` as :class:`PatchStore`'s."""

    def __init__(self, tile_dir: str | Path):
        self.tile_dir = Path(tile_dir)
        recorded.ensure_local(self.tile_dir / PATCHES_FILE)
        table, pmeta = _patches_table(self.tile_dir)
        self._patches = table_columns(table, PATCH_DTYPES, PATCH_DTYPES)
        self.meta = TileMeta(tile=pmeta["tile"], patch_size_m=tuple(pmeta["patch_size_m"]), crs=pmeta.get("crs"))
        """The tile's identity as a side table records it (no texture list: that is the faces table's)."""

    def patches(self) -> dict[str, np.ndarray]:
        return dict(self._patches)

    def side(self, name: str) -> dict[str, np.ndarray] | None:
        got = read_side_table(self.tile_dir, name, self._patches["patch"])
        return None if got is None else got[0]


def read_side_table(tile_dir: str | Path, name: str, patch_keys: np.ndarray | None = None) -> tuple[dict, dict] | None:
    """A tile's side table as (columns, metadata), or None when it was never written.

    patch_keys: the patches table's ``patch`` column; a side table whose keys differ is stale (written
    for an older partition) and raises InputError rather than being joined to the wrong patches.
    """
    path = side_table_path(tile_dir, name)
    if not recorded.is_file(path):
        return None
    recorded.ensure_local(path)
    pf, meta = open_table(path, name)
    try:
        cols = table_columns(pf.read(), SIDE_TABLES[name], SIDE_TABLES[name])
    except (OSError, pa.ArrowException) as exc:
        raise InputError(path, f"cannot read ({exc})") from None
    if patch_keys is not None and not np.array_equal(cols["patch"], patch_keys):
        raise InputError(path, f"{name} do not match the tile's patches (stale): re-run `ms3d run`")
    return cols, meta
