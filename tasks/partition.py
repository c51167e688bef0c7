"""Partition points and mesh faces into the global 3D patch grid (Liu et al. 2023, §3.2.1, Alg. 1 and 2).

The grid is global and anchored at the campus origin: patch ``(i, j, k) = floor(xyz / patch_size_m)``,
computed in float64 from campus-local metres, so the same patch has the same id in every tile and run.
The paper anchors its grid at the data's minimum corner; a global anchor gives the same cells up to a
shift and lets tiles be processed independently.

- Points and mesh vertices go to the patch that contains them (Algorithm 2).
- Faces go to the patch that contains their centroid (Algorithm 1).
- A patch belongs to the ground tile that contains its centre, so no patch is split between tiles.

A patch is named on disk by a packed int64 key: three biased 21-bit fields, ``i`` highest, so ascending
keys sort patches by ``(i, j, k)``. Valid for ``|i|, |j|, |k| < 2**20`` (about 2400 km at 2.3 m).

Worked example (default 2.3 x 1.0 x 0.7 m patches)::

    >>> patch_index(np.array([[5.0, 2.5, 1.0], [-0.1, -0.1, -0.1]]), (2.3, 1.0, 0.7)).tolist()
    [[2, 2, 1], [-1, -1, -1]]
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FIELD_BITS = 21
BIAS = 1 << (FIELD_BITS - 1)  # 2**20: biased fields are non-negative
FIELD_MASK = (1 << FIELD_BITS) - 1

FACE_VERTEX_COLUMNS = ("x0", "y0", "z0", "x1", "y1", "z1", "x2", "y2", "z2")


def _size(patch_size) -> np.ndarray:
    size = np.asarray(patch_size, dtype=np.float64).reshape(3)
    if not (size > 0).all():
        raise ValueError(f"patch sizes must be positive, got {size.tolist()}")
    return size


def _check_range(ijk_f: np.ndarray) -> None:
    """ijk_f: float64 cell indices; rejects NaN/inf and cells outside the packable range."""
    if ijk_f.size == 0:
        return
    lo, hi = ijk_f.min(), ijk_f.max()  # NaN propagates, so the comparisons below catch it
    if not (lo >= -BIAS and hi < BIAS):
        raise ValueError(
            f"patch indices span [{lo}, {hi}]: coordinates are NaN/inf or farther than 2**20 patches "
            "from the campus origin (not campus-local metres?)"
        )


def _cells(x: np.ndarray, y: np.ndarray, z: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Per-axis floor(coord / size) in float64 -> (n, 3) int32 (column-major, so each axis is contiguous).

    x, y, z: (n,) any float dtype.
    """
    out = np.empty((len(x), 3), dtype=np.int32, order="F")
    q = np.empty(len(x), dtype=np.float64)
    for axis, c in enumerate((x, y, z)):  # per axis: three passes, no (n, 3) float64 temporary
        np.divide(c, size[axis], out=q)
        np.floor(q, out=q)
        _check_range(q)
        out[:, axis] = q
    return out


def patch_index(xyz: np.ndarray, patch_size) -> np.ndarray:
    """Patch cell of each point.

    Args:
        xyz: (n, 3) float32/float64, metres, campus-local.
        patch_size: (3,) patch edge lengths in metres (default config: 2.3, 1.0, 0.7).
    Returns:
        (n, 3) int32 ``floor(xyz / patch_size)`` computed in float64.
    Raises:
        ValueError: NaN/inf coordinates or cells beyond +-2**20.
    """
    xyz = np.asarray(xyz)
    if xyz.ndim != 2 or xyz.shape[1] != 3:
        raise ValueError(f"xyz must be (n, 3), got {xyz.shape}")
    return _cells(xyz[:, 0], xyz[:, 1], xyz[:, 2], _size(patch_size))


def vertex_patches(vertices: np.ndarray, patch_size) -> np.ndarray:
    """Patch of each mesh vertex (the patch containing it, as for points). vertices: (v, 3) -> (v, 3) int32."""
    return patch_index(vertices, patch_size)


def _face_cells(x0, y0, z0, x1, y1, z1, x2, y2, z2, size: np.ndarray) -> np.ndarray:
    """Cell of each face centroid; centroid summed in float64 so every caller gets identical cells."""
    cx = (np.asarray(x0, np.float64) + x1 + x2) / 3.0
    cy = (np.asarray(y0, np.float64) + y1 + y2) / 3.0
    cz = (np.asarray(z0, np.float64) + z1 + z2) / 3.0
    return _cells(cx, cy, cz, size)


def face_patches(triangles: np.ndarray, patch_size) -> np.ndarray:
    """Patch of each face = patch containing its centroid (Algorithm 1).

    Args:
        triangles: (m, 3, 3) float32/float64, metres, campus-local; ``triangles[f, v]`` is vertex v of face f.
    Returns:
        (m, 3) int32 patch indices.
    """
    t = np.asarray(triangles)
    if t.ndim != 3 or t.shape[1:] != (3, 3):
        raise ValueError(f"triangles must be (m, 3, 3), got {t.shape}")
    return _face_cells(*(t[:, v, a] for v in range(3) for a in range(3)), _size(patch_size))


def pack_patch_key(ijk: np.ndarray) -> np.ndarray:
    """(n, 3) int patch indices -> (n,) int64 keys; bijective for |i|, |j|, |k| < 2**20.

    Ascending keys order patches by (i, j, k) lexicographically.
    """
    ijk = np.asarray(ijk)
    if ijk.ndim != 2 or ijk.shape[1] != 3:
        raise ValueError(f"ijk must be (n, 3), got {ijk.shape}")
    b = ijk.astype(np.int64) + BIAS
    if b.size and (b.min() < 0 or b.max() > FIELD_MASK):
        raise ValueError("patch indices must satisfy -2**20 <= i, j, k < 2**20")
    return (b[:, 0] << (2 * FIELD_BITS)) | (b[:, 1] << FIELD_BITS) | b[:, 2]


def unpack_patch_key(keys: np.ndarray) -> np.ndarray:
    """(n,) int64 keys -> (n, 3) int32 patch indices (inverse of :func:`pack_patch_key`)."""
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    out = np.empty((len(keys), 3), dtype=np.int32)
    out[:, 0] = ((keys >> (2 * FIELD_BITS)) & FIELD_MASK) - BIAS
    out[:, 1] = ((keys >> FIELD_BITS) & FIELD_MASK) - BIAS
    out[:, 2] = (keys & FIELD_MASK) - BIAS
    return out


def patch_centre(ijk: np.ndarray, patch_size) -> np.ndarray:
    """(n, 3) int patch indices -> (n, 3) float64 patch centres, metres, campus-local."""
    return (np.asarray(ijk, dtype=np.float64) + 0.5) * _size(patch_size)


def tile_of_patch(ijk: np.ndarray, patch_size, tile_size_m: float) -> np.ndarray:
    """Ground tile (ix, iy) of each patch: the tile containing the patch centre.

    Args:
        ijk: (n, 3) int patch indices.
        tile_size_m: ground tile edge, metres (default config 100).
    Returns:
        (n, 2) int32 tile indices, tile (ix, iy) covering [ix*t, (ix+1)*t) x [iy*t, (iy+1)*t).
    """
    if not tile_size_m > 0:
        raise ValueError(f"tile_size_m must be positive, got {tile_size_m}")
    centre = patch_centre(ijk, patch_size)[:, :2]
    return np.floor(centre / float(tile_size_m)).astype(np.int32)


def tile_of_points(xyz: np.ndarray, patch_size, tile_size_m: float) -> np.ndarray:
    """Tile of the patch containing each point (how ingest routes points). xyz: (n, 3) -> (n, 2) int32."""
    return tile_of_patch(patch_index(xyz, patch_size), patch_size, tile_size_m)


def tile_of_faces(triangles: np.ndarray, patch_size, tile_size_m: float) -> np.ndarray:
    """Tile of the patch containing each face centroid. triangles: (m, 3, 3) -> (m, 2) int32."""
    return tile_of_patch(face_patches(triangles, patch_size), patch_size, tile_size_m)


@dataclass(frozen=True)
class Partition:
    """Rows grouped by patch.

    Attributes:
        order: (n,) int64 permutation; ``rows[order]`` sorts rows by patch key, stable (rows of one patch
            keep their input order).
        keys: (u,) int64 unique packed patch keys, ascending.
        starts, stops: (u,) int64; the sorted rows ``starts[p]:stops[p]`` lie in patch ``keys[p]``.
            The ranges are non-empty and tile ``0:n`` in order.
    """

    order: np.ndarray
    keys: np.ndarray
    starts: np.ndarray
    stops: np.ndarray

    @property
    def n_rows(self) -> int:
        return len(self.order)

    @property
    def counts(self) -> np.ndarray:
        """(u,) int64 rows per patch."""
        return self.stops - self.starts

    @property
    def ijk(self) -> np.ndarray:
        """(u, 3) int32 patch indices of ``keys``."""
        return unpack_patch_key(self.keys)

    def sorted_keys(self) -> np.ndarray:
        """(n,) int64 patch key of each sorted row."""
        return np.repeat(self.keys, self.counts)

    def __repr__(self) -> str:
        return f"Partition(n_rows={self.n_rows}, n_patches={len(self.keys)})"


def _empty_partition() -> Partition:
    e = np.zeros(0, dtype=np.int64)
    return Partition(order=e, keys=e.copy(), starts=e.copy(), stops=e.copy())


def partition_cells(ijk: np.ndarray) -> Partition:
    """Group rows by their patch cell.

    Args:
        ijk: (n, 3) int patch index of each row.
    Returns:
        :class:`Partition` (stable order, ascending keys).

    The sort key is the row's cell rank inside the bounding box of the cells (same order as the packed
    key), shifted left with the row number in the low bits: one in-place ``np.sort`` of int64 (SIMD on
    x86) then yields a stable argsort. Measured on 5 M shuffled points: 0.15 s, against 0.51 s for
    ``np.argsort`` (quicksort, unstable) and 1.27 s for ``np.argsort(kind="stable")`` of the packed keys.
    When the rank and the row number do not fit 63 bits together, it falls back to the stable argsort.
    """
    ijk = np.asarray(ijk)
    n = len(ijk)
    if n == 0:
        return _empty_partition()
    # per-column reductions: ~20x faster than ijk.min(axis=0) on a C-ordered (n, 3) array
    lo = np.array([ijk[:, a].min() for a in range(3)], dtype=np.int64)
    ext = np.array([ijk[:, a].max() for a in range(3)], dtype=np.int64) - lo + 1
    row_bits = max(1, (n - 1).bit_length())
    cell_bits = max(1, (int(ext[0]) * int(ext[1]) * int(ext[2]) - 1).bit_length())
    if row_bits + cell_bits <= 63:
        rank = ijk[:, 0] - lo[0]  # int64 from here on (lo is int64)
        rank *= ext[1]
        rank += ijk[:, 1]
        rank -= lo[1]
        rank *= ext[2]
        rank += ijk[:, 2]
        rank -= lo[2]
        rank <<= row_bits
        rank |= np.arange(n, dtype=np.int64)
        rank.sort()
        order = rank & ((1 << row_bits) - 1)
        rank >>= row_bits
        sorted_rank = rank
    else:
        packed = pack_patch_key(ijk)
        order = np.argsort(packed, kind="stable").astype(np.int64, copy=False)
        sorted_rank = packed[order]
    change = np.flatnonzero(sorted_rank[1:] != sorted_rank[:-1]) + 1
    starts = np.concatenate(([0], change)).astype(np.int64)
    stops = np.concatenate((change, [n])).astype(np.int64)
    keys = pack_patch_key(ijk[order[starts]])
    return Partition(order=order, keys=keys, starts=starts, stops=stops)


def partition_points(xyz: np.ndarray, patch_size) -> Partition:
    """Algorithm 2: each point to the patch that contains it.

    xyz: (n, 3) float32/float64, metres, campus-local.
    """
    return partition_cells(patch_index(xyz, patch_size))


def partition_faces(triangles: np.ndarray, patch_size) -> Partition:
    """Algorithm 1: each face to the patch that contains its centroid.

    triangles: (m, 3, 3) float32/float64, metres, campus-local.
    """
    return partition_cells(face_patches(triangles, patch_size))


def merge_pair_index(point_part: Partition, face_part: Partition):
    """Pair point patches with mesh patches of the same cell.

    Returns:
        keys: (u,) int64 union of both sides' keys, ascending.
        point_ranges: (u, 2) int64 [start, stop) into the sorted points; start == stop where the patch has
            no points (placed at the insertion row, so ranges stay ordered and contiguous).
        face_ranges: (u, 2) int64 likewise into the sorted faces.
    """
    keys = np.concatenate((point_part.keys, face_part.keys)).astype(np.int64, copy=False)
    keys.sort()  # both inputs are sorted and unique: a diff mask is enough (np.union1d hashes, ~10x slower)
    keys = keys[np.concatenate(([True], keys[1:] != keys[:-1]))] if len(keys) else keys
    return keys, _ranges_for(point_part, keys), _ranges_for(face_part, keys)


def _ranges_for(part: Partition, keys: np.ndarray) -> np.ndarray:
    pos = np.searchsorted(part.keys, keys)
    u = len(part.keys)
    found = pos < u
    found[found] = part.keys[pos[found]] == keys[found]
    # empty ranges sit at the row where the patch would start
    insert_row = np.append(part.starts, part.n_rows)[pos]
    out = np.empty((len(keys), 2), dtype=np.int64)
    out[:, 0] = insert_row
    out[:, 1] = insert_row
    out[found, 1] = part.stops[pos[found]]
    return out


def _float32_coords(cols: dict, names, table: str) -> dict:
    """Coordinates cast to float32 first, so keys are computed from exactly the values that get stored."""
    missing = [c for c in names if c not in cols]
    if missing:
        raise ValueError(f"{table} columns need {', '.join(names)}; missing {missing}")
    return {**cols, **{c: np.asarray(cols[c]).astype(np.float32, copy=False) for c in names}}


def _sorted_columns(cols: dict | None, part: Partition) -> dict:
    if cols is None:
        return {}
    lengths = {k: len(v) for k, v in cols.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"columns differ in length: {lengths}")
    out = {k: np.take(np.asarray(v), part.order) for k, v in cols.items() if k != "patch"}
    out["patch"] = part.sorted_keys()
    return out


def _segment_bbox(lo: list, hi: list, part: Partition) -> tuple[np.ndarray, np.ndarray]:
    """Per-patch min of ``lo`` arrays and max of ``hi`` arrays (each a list of 3 sorted (n,) arrays)."""
    u = len(part.keys)
    mins = np.full((u, 3), np.nan, dtype=np.float32)
    maxs = np.full((u, 3), np.nan, dtype=np.float32)
    if u:
        for a in range(3):  # ranges are non-empty, so reduceat is exact
            mins[:, a] = np.minimum.reduceat(lo[a], part.starts)
            maxs[:, a] = np.maximum.reduceat(hi[a], part.starts)
    return mins, maxs


def build_tile_tables(points_cols: dict | None, faces_cols: dict | None, patch_size):
    """Partition one tile's points and faces; return the columns of points, faces and patches tables.

    Args:
        points_cols: {"x", "y", "z": (n,) float32 campus-local metres, any other (n,) columns} or None.
        faces_cols: {"x0".."z2": (m,) float32 campus-local metres, any other (m,) columns} or None.
            Coordinates of another dtype are cast to float32 before keying (that is what gets stored).
        patch_size: (3,) metres.
    Returns:
        (points, faces, patches): points/faces are the input columns gathered into patch order plus
        ``patch`` (int64 packed key per row) ({} when the input was None); patches has one row per
        patch with points or faces: patch int64, i/j/k int32, n_points/n_faces int32, point_start,
        point_stop, face_start, face_stop int64, xmin..zmax float32 (bbox of the points and face
        vertices; NaN if both empty), outlier_points/outlier_faces/outlier bool (False: set by the
        outlier stage), label int8 (-1 unknown), score float32 (NaN until graded).
    """
    size = _size(patch_size)
    p_part = f_part = _empty_partition()
    if points_cols is not None:
        points_cols = _float32_coords(points_cols, ("x", "y", "z"), "points")
        p_part = partition_cells(_cells(points_cols["x"], points_cols["y"], points_cols["z"], size))
    if faces_cols is not None:
        faces_cols = _float32_coords(faces_cols, FACE_VERTEX_COLUMNS, "faces")
        f_part = partition_cells(_face_cells(*(faces_cols[c] for c in FACE_VERTEX_COLUMNS), size))
    points = _sorted_columns(points_cols, p_part)
    faces = _sorted_columns(faces_cols, f_part)

    keys, pr, fr = merge_pair_index(p_part, f_part)
    u = len(keys)
    ijk = unpack_patch_key(keys)
    bmin = np.full((u, 3), np.nan, dtype=np.float32)
    bmax = np.full((u, 3), np.nan, dtype=np.float32)
    if p_part.n_rows:
        xyz = [points[c].astype(np.float32, copy=False) for c in ("x", "y", "z")]
        mn, mx = _segment_bbox(xyz, xyz, p_part)
        at = np.searchsorted(keys, p_part.keys)
        bmin[at], bmax[at] = mn, mx
    if f_part.n_rows:
        vx = [[faces[f"{a}{v}"].astype(np.float32, copy=False) for v in range(3)] for a in "xyz"]
        lo = [np.minimum(np.minimum(c[0], c[1]), c[2]) for c in vx]
        hi = [np.maximum(np.maximum(c[0], c[1]), c[2]) for c in vx]
        mn, mx = _segment_bbox(lo, hi, f_part)
        at = np.searchsorted(keys, f_part.keys)
        bmin[at] = np.fmin(bmin[at], mn)
        bmax[at] = np.fmax(bmax[at], mx)
    patches = {
        "patch": keys,
        "i": ijk[:, 0].copy(),
        "j": ijk[:, 1].copy(),
        "k": ijk[:, 2].copy(),
        "n_points": (pr[:, 1] - pr[:, 0]).astype(np.int32),
        "n_faces": (fr[:, 1] - fr[:, 0]).astype(np.int32),
        "point_start": pr[:, 0].copy(),
        "point_stop": pr[:, 1].copy(),
        "face_start": fr[:, 0].copy(),
        "face_stop": fr[:, 1].copy(),
        "xmin": bmin[:, 0].copy(), "ymin": bmin[:, 1].copy(), "zmin": bmin[:, 2].copy(),
        "xmax": bmax[:, 0].copy(), "ymax": bmax[:, 1].copy(), "zmax": bmax[:, 2].copy(),
        "outlier_points": np.zeros(u, dtype=bool),
        "outlier_faces": np.zeros(u, dtype=bool),
        "outlier": np.zeros(u, dtype=bool),
        "label": np.full(u, -1, dtype=np.int8),
        "score": np.full(u, np.nan, dtype=np.float32),
    }
    return points, faces, patches
