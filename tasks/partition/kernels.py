"""Partition points and mesh faces into the global 3D patch grid (Liu et al. 2023, §3.2.1, Alg. 1 and 2).

The grid is :class:`storage.grid.PatchGrid`: anchored in projected world coordinates, so the same place
has the same patch id in every tile, run and campus extent. The paper anchors its grid at the data's
minimum corner; a world anchor gives the same cells up to a shift and lets tiles be processed
independently.

- Points go to the patch that contains them (Algorithm 2).
- Faces go to the patch that contains their centroid (Algorithm 1, step 2).
- Each face corner records the patch that contains its vertex (Algorithm 1, step 3): ``vp0..vp2``.
- A patch belongs to the ground tile that contains its centre, so no patch is split between tiles.

Cells are computed in float64 from the stored float32 campus-local values plus the float64 campus
origin, so every stage that starts from the stored values gets the same cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from storage.contracts.staging import FACE_VERTEX_COLUMNS
from storage.grid import PatchGrid
from tasks.geometry.cells import Partition, empty_partition, partition_cells


def point_cells(xyz: np.ndarray, grid: PatchGrid, origin) -> np.ndarray:
    """Algorithm 2: cell of each point. xyz: (n, 3) campus-local metres -> (n, 3) int64."""
    return grid.cells_local(np.asarray(xyz, dtype=np.float32), origin)


def face_cells(triangles: np.ndarray, grid: PatchGrid, origin) -> np.ndarray:
    """Algorithm 1: cell of each face centroid. triangles: (m, 3, 3) campus-local metres -> (m, 3) int64."""
    t = np.asarray(triangles, dtype=np.float32)
    if t.ndim != 3 or t.shape[1:] != (3, 3):
        raise ValueError(f"triangles must be (m, 3, 3), got {t.shape}")
    return grid.face_cells([t[:, v, a] for v in range(3) for a in range(3)], origin)


def tile_of_points(xyz: np.ndarray, grid: PatchGrid, origin) -> np.ndarray:
    """Tile of the patch holding each point (how ingest routes points). (n, 3) -> (n, 2) int64."""
    return grid.tile_of_cells(point_cells(xyz, grid, origin))


def tile_of_faces(triangles: np.ndarray, grid: PatchGrid, origin) -> np.ndarray:
    """Tile of the patch holding each face centroid. (m, 3, 3) -> (m, 2) int64."""
    return grid.tile_of_cells(face_cells(triangles, grid, origin))


def partition_points(xyz: np.ndarray, grid: PatchGrid, origin) -> Partition:
    """Algorithm 2: each point to the patch that contains it. xyz: (n, 3) campus-local metres."""
    return partition_cells(point_cells(xyz, grid, origin))


def partition_faces(triangles: np.ndarray, grid: PatchGrid, origin) -> Partition:
    """Algorithm 1: each face to the patch that contains its centroid. triangles: (m, 3, 3) campus-local."""
    return partition_cells(face_cells(triangles, grid, origin))


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


def _partition_of(cols: dict, compute) -> Partition:
    """Rows grouped by patch: by the ``patch`` keys ingest computed in float64 world coordinates when the
    columns carry them (so a place keeps its patch whatever the campus origin; concatenated sorted runs,
    so a stable argsort of the keys merges them in O(n log runs)), else by cells from the columns."""
    if "patch" in cols:
        keys = np.asarray(cols["patch"], np.int64)
        order = np.argsort(keys, kind="stable").astype(np.int64, copy=False)
        sk = keys[order]
        change = np.flatnonzero(sk[1:] != sk[:-1]) + 1
        starts = np.concatenate(([0], change)).astype(np.int64)
        stops = np.concatenate((change, [len(sk)])).astype(np.int64)
        return Partition(order=order, keys=sk[starts] if len(sk) else sk, starts=starts if len(sk) else starts[:0],
                         stops=stops if len(sk) else stops[:0])
    return partition_cells(compute(cols))


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


def merge_runs(pieces: list[dict[str, np.ndarray]]) -> tuple[dict[str, np.ndarray], Partition]:
    """Merge sorted runs into one table sorted by ``patch``, stably (run order, then row order).

    pieces: column dicts, each sorted by its int64 ``patch`` column, same columns and dtypes. Each run's
    rows are scattered straight to their places (their target positions ascend within a run), so the
    columns are copied once, never concatenated first. Returns (sorted columns, Partition).
    """
    keys = np.concatenate([p["patch"] for p in pieces]) if pieces else np.zeros(0, np.int64)
    part = _partition_of({"patch": keys}, None)
    n = len(keys)
    pos = np.empty(n, np.int64)
    pos[part.order] = np.arange(n, dtype=np.int64)
    out = {}
    for name in (pieces[0] if pieces else {}):
        if name == "patch":
            continue
        col = np.empty(n, dtype=np.asarray(pieces[0][name]).dtype)
        at = 0
        for p in pieces:
            m = len(p[name])
            col[pos[at:at + m]] = p[name]
            at += m
        out[name] = col
    out["patch"] = part.sorted_keys()
    return out, part


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


@dataclass(frozen=True)
class SideSummary:
    """Per-patch facts of one side (points or faces) of a tile, in ascending key order.

    keys: (u,) int64; counts: (u,) int64 rows per patch; bmin, bmax: (u, 3) float32 bbox of the rows'
    coordinates (points) or face vertices (faces), campus-local metres.
    """

    keys: np.ndarray
    counts: np.ndarray
    bmin: np.ndarray
    bmax: np.ndarray

    @staticmethod
    def empty() -> SideSummary:
        return SideSummary(np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3), np.float32),
                           np.zeros((0, 3), np.float32))

    @staticmethod
    def concat(parts: list[SideSummary]) -> SideSummary:
        """Summaries of consecutive, disjoint key ranges (e.g. the blocks of a streamed tile)."""
        if not parts:
            return SideSummary.empty()
        return SideSummary(*(np.concatenate([getattr(p, f) for p in parts])
                             for f in ("keys", "counts", "bmin", "bmax")))


def summarise_side(sorted_cols: dict, part: Partition, faces: bool) -> SideSummary:
    """The :class:`SideSummary` of rows sorted by ``part`` (sorted_cols: the gathered columns)."""
    if part.n_rows == 0:
        return SideSummary.empty()
    if faces:
        vx = [[sorted_cols[f"{a}{v}"].astype(np.float32, copy=False) for v in range(3)] for a in "xyz"]
        lo = [np.minimum(np.minimum(c[0], c[1]), c[2]) for c in vx]
        hi = [np.maximum(np.maximum(c[0], c[1]), c[2]) for c in vx]
    else:
        lo = hi = [sorted_cols[c].astype(np.float32, copy=False) for c in ("x", "y", "z")]
    mn, mx = _segment_bbox(lo, hi, part)
    return SideSummary(part.keys, part.counts, mn, mx)


def patches_table(points: SideSummary, faces: SideSummary) -> dict[str, np.ndarray]:
    """The patches table of a tile from its two sides: one row per patch with points or faces, ascending
    keys; row ranges point into the sorted points / faces tables (empty ranges at the insertion row)."""
    keys = np.concatenate((points.keys, faces.keys)).astype(np.int64, copy=False)
    keys.sort()
    keys = keys[np.concatenate(([True], keys[1:] != keys[:-1]))] if len(keys) else keys
    u = len(keys)
    ijk = PatchGrid.unpack(keys)
    out = {"patch": keys, "i": ijk[:, 0].copy(), "j": ijk[:, 1].copy(), "k": ijk[:, 2].copy()}
    bmin = np.full((u, 3), np.nan, dtype=np.float32)
    bmax = np.full((u, 3), np.nan, dtype=np.float32)
    ranges = {}
    for name, side in (("point", points), ("face", faces)):
        at = np.searchsorted(keys, side.keys)
        counts = np.zeros(u, np.int64)
        counts[at] = side.counts
        stop = np.cumsum(counts)
        ranges[name] = (stop - counts, stop, counts)
        if len(at):
            bmin[at] = np.fmin(bmin[at], side.bmin)
            bmax[at] = np.fmax(bmax[at], side.bmax)
    out["n_points"] = ranges["point"][2].astype(np.int32)
    out["n_faces"] = ranges["face"][2].astype(np.int32)
    out["point_start"], out["point_stop"] = ranges["point"][0], ranges["point"][1]
    out["face_start"], out["face_stop"] = ranges["face"][0], ranges["face"][1]
    for a, axis in enumerate("xyz"):
        out[f"{axis}min"] = bmin[:, a].copy()
    for a, axis in enumerate("xyz"):
        out[f"{axis}max"] = bmax[:, a].copy()
    return out


def build_tile_tables(points_cols: dict | None, faces_cols: dict | None, grid: PatchGrid, origin):
    """Partition one tile's points and faces; return the columns of the points, faces and patches tables.

    Args:
        points_cols: {"x", "y", "z": (n,) float32 campus-local metres, any other (n,) columns} or None.
        faces_cols: {"x0".."z2": (m,) float32 campus-local metres, any other (m,) columns} or None.
            A ``patch`` column (int64 keys, computed by ingest from float64 world coordinates) is used
            as given; without one, keys are computed from the coordinates cast to float32. Likewise
            ``vp0..vp2`` of faces.
        grid: the campus patch grid; origin: (3,) float64 campus origin, world metres.
    Returns:
        (points, faces, patches): points/faces are the input columns gathered into patch order plus
        ``patch`` (int64 key per row), and for faces ``vp0, vp1, vp2`` (int64 key of the patch holding
        each corner vertex, Algorithm 1 step 3) ({} when the input was None); patches (:func:`patches_table`)
        has one row per patch with points or faces: patch int64, i/j/k int64 world cells, n_points/n_faces
        int32, point_start, point_stop, face_start, face_stop int64, xmin..zmax float32 (bbox of the points
        and face vertices, campus-local).
    """
    points, faces, p_side, f_side = partition_sides(points_cols, faces_cols, grid, origin)
    return points, faces, patches_table(p_side, f_side)


def partition_sides(points_cols: dict | None, faces_cols: dict | None, grid: PatchGrid, origin):
    """Sort both sides by patch: (points, faces, points SideSummary, faces SideSummary)."""
    p_part = f_part = empty_partition()
    if points_cols is not None:
        points_cols = _float32_coords(points_cols, ("x", "y", "z"), "points")
        p_part = _partition_of(points_cols, lambda c: grid.cells(c["x"], c["y"], c["z"], origin))
    if faces_cols is not None:
        faces_cols = _float32_coords(faces_cols, FACE_VERTEX_COLUMNS, "faces")
        f_part = _partition_of(faces_cols, lambda c: grid.face_cells([c[k] for k in FACE_VERTEX_COLUMNS], origin))
    points = _sorted_columns(points_cols, p_part)
    faces = _sorted_columns(faces_cols, f_part)
    if faces and "vp0" not in faces:
        for v in range(3):
            faces[f"vp{v}"] = grid.pack(grid.cells(faces[f"x{v}"], faces[f"y{v}"], faces[f"z{v}"], origin))
    return points, faces, summarise_side(points, p_part, False), summarise_side(faces, f_part, True)
