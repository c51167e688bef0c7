"""Geometric evidence beside the network: where the MLS points lie off the mesh, the mesh is wrong.

The network grades a pair by its look; a city model (LoD2 block, CAD) looks clean everywhere and is
graded good although the street scan shows recesses, balconies and passages the model lacks. Two rules
read that directly from the distances of a patch's MLS points to the mesh (metres, campus-local):

- **off surface** (a pair): an upper quantile (``quantile``, 0.95: a window recess is a small share of
  a wall patch's points) of the distances of the patch's points to the faces of the patch and its
  26-neighbours exceeds ``off_surface_m``, and at least ``min_off_points`` points lie beyond it; the
  points then belong to a surface the mesh does not have (a recess behind the modelled wall, a balcony
  in front of it, a passage inside the solid);
- **missing surface** (points but no faces): the patch's points lie off the mesh by the same test, yet
  within ``near_m`` of it: the patch sits against the modelled surface (a balcony in front of a wall),
  not in open ground or trees far from any face;
- **inside the solid** (points but no faces): at least ``inside_share`` of the patch's measured points
  (and ``min_points``) are enclosed by the mesh (:func:`inside_solid`): a scanner cannot see inside a
  solid, so the model lacks an opening there (a passage through a city model's block). Far from any
  face, so the rule above cannot see it.

Both need ``min_points`` counted points in the patch. The nearest face of a point counts when its patch
is the point's patch or one of its 26-neighbours, or when it is within ``near_m`` (a balcony deeper
than a patch); else the point's distance is ``inf``. A point off the surface whose nearest face is flat
(``|n_z| > standing_normal_z``: ground, flat roof) is a thing standing on it (car, person, bush) and
does not count; a patch where most points are such things gives no evidence. At most
``max_points_per_patch`` points of each patch are measured (an even stride through the patch's rows).
No I/O here: :mod:`tasks.classify.stage` reads the tile.

    >>> import numpy as np
    >>> v, f = np.array([[0, 0, 0], [2, 0, 0], [0, 0, 2]], float), np.array([[0, 1, 2]])  # a wall, y = 0
    >>> ijk = np.array([[0, 0, 0], [0, -1, 0]])                               # its patch, and the one in front
    >>> pts = np.array([[0.3, -0.4, 0.3]] * 5 + [[0.3, -1.2, 0.3]] * 5)       # 0.4 m and 1.2 m in front
    >>> ev = offset_evidence(pts, np.repeat([0, 1], 5), v, f, np.array([0]), ijk, min_points=5)
    >>> np.round(ev.offset_m.astype(float), 2).tolist(), ev.bad.tolist()
    ([0.4, 1.2], [True, True])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tasks.geometry.distance import point_to_mesh_distance, unit_face_normals

MAX_POINTS_PER_PATCH = 200  # points of a patch the rules measure (an even stride through its rows)


@dataclass(frozen=True)
class Evidence:
    """Per patch (U,): ``offset_m`` float32 robust distance of its points to the neighbourhood's faces
    (NaN: too few points or no faces in the tile; inf: no face in the 26-neighbourhood), ``bad`` bool
    (either rule fires), ``missing`` bool (the points-only rule fired)."""

    offset_m: np.ndarray
    bad: np.ndarray
    missing: np.ndarray


def range_rows(start: np.ndarray, stop: np.ndarray, n: int) -> np.ndarray:
    """(n,) int64 row of each element of a table whose rows ``start[r]:stop[r]`` belong to patch r (-1: none).

    >>> range_rows(np.array([0, 3]), np.array([2, 4]), 5).tolist()
    [0, 0, -1, 1, -1]
    """
    out = np.full(n, -1, np.int64)
    count = np.asarray(stop, np.int64) - np.asarray(start, np.int64)
    idx = np.repeat(np.asarray(start, np.int64) - np.r_[0, np.cumsum(count)[:-1]], count) + np.arange(count.sum())
    out[idx] = np.repeat(np.arange(len(count)), count)
    return out


def _strided_rows(point_row: np.ndarray, max_per_row: int) -> np.ndarray:
    """Indices of at most ~``max_per_row`` evenly strided points of each row (point_row sorted)."""
    n = len(point_row)
    if n == 0:
        return np.zeros(0, np.int64)
    start = np.r_[0, np.flatnonzero(np.diff(point_row)) + 1]
    count = np.diff(np.r_[start, n])
    rank = np.arange(n) - np.repeat(start, count)
    stride = np.repeat(np.maximum(1, -(-count // max_per_row)), count)
    return np.flatnonzero(rank % stride == 0)


def strided_ranges(start: np.ndarray, stop: np.ndarray, max_per_row: int) -> tuple[np.ndarray, np.ndarray]:
    """The points :func:`offset_evidence` measures, from the row ranges alone: (indices into the points
    table, row of each), the same evenly strided ones as it picks itself, without a per-point array.

    >>> idx, row = strided_ranges(np.array([0, 5]), np.array([5, 6]), 2)
    >>> idx.tolist(), row.tolist()
    ([0, 3, 5], [0, 0, 1])
    """
    start, stop = np.asarray(start, np.int64), np.asarray(stop, np.int64)
    count = np.maximum(stop - start, 0)
    stride = np.maximum(1, -(-count // max_per_row))
    take = -(-count // stride)
    row = np.repeat(np.arange(len(count)), take)
    rank = np.arange(int(take.sum())) - np.repeat(np.cumsum(take) - take, take)
    return start[row] + rank * stride[row], row


def _group_quantile(values: np.ndarray, group: np.ndarray, n_groups: int, q: float) -> tuple[np.ndarray, np.ndarray]:
    """(n_groups,) lower ``q`` quantile of ``values`` per group (NaN for empty groups) and the counts."""
    order = np.lexsort((values, group))
    g, v = group[order], values[order]
    count = np.bincount(g, minlength=n_groups)
    start = np.r_[0, np.cumsum(count)[:-1]]
    out = np.full(n_groups, np.nan)
    has = count > 0
    out[has] = v[start[has] + np.floor(q * (count[has] - 1)).astype(np.int64)]
    return out, count


def offset_evidence(points: np.ndarray, point_row: np.ndarray, vertices: np.ndarray, faces: np.ndarray,
                    face_row: np.ndarray, ijk: np.ndarray, n_faces: np.ndarray | None = None, *,
                    n_points: np.ndarray | None = None, off_surface_m: float = 0.22, near_m: float = 1.5,
                    quantile: float = 0.95, min_points: int = 5, max_points_per_patch: int = MAX_POINTS_PER_PATCH,
                    standing_normal_z: float = 0.7, min_off_points: int = 3, inside_share: float = 0.5) -> Evidence:
    """The two evidence rules (module doc) over the U patches of a tile.

    points: (n, 3) float64 metres; point_row: (n,) int64 patch row of each point, sorted ascending;
    vertices: (v, 3) float64 metres, same frame; faces: (m, 3) int64 into them; face_row: (m,) int64 patch
    row of each face; ijk: (U, 3) int64 patch cells; n_faces: (U,) faces per patch (default: counted from
    ``face_row``); n_points: (U,) points per patch when ``points`` is already the measured sample
    (:func:`strided_ranges`; default: ``points`` are all of them, and the sample is picked here).
    """
    u = len(ijk)
    ijk = np.asarray(ijk, np.int64)
    n_faces = np.bincount(face_row, minlength=u) if n_faces is None else np.asarray(n_faces)
    if len(points) == 0 or len(faces) == 0:
        z = np.zeros(u, bool)
        return Evidence(np.full(u, np.nan, np.float32), z, z.copy())
    if n_points is None:
        sel = _strided_rows(point_row, max_points_per_patch)
        n_points = np.bincount(point_row, minlength=u)
        points, point_row = points[sel], point_row[sel]
    rows = point_row
    d, fid = point_to_mesh_distance(points, vertices, faces, return_faces=True)
    f = np.maximum(fid, 0)
    near = (fid >= 0) & ((np.abs(ijk[face_row[f]] - ijk[rows]).max(axis=1) <= 1) | (d <= near_m))
    d = np.where(near, d, np.inf)
    # a point nearest an upward face (ground, flat roof) off the surface is a thing standing on it: a car,
    # a person, a bush, street furniture; no evidence about the building, so it does not count
    # (|n_z|: a mesh's orientation is not trusted)
    nz = np.abs(unit_face_normals(vertices, faces)[:, 2])
    standing = near & (nz[f] > standing_normal_z) & (d > off_surface_m)
    keep = ~standing
    offset, n_pts = _group_quantile(d[keep], rows[keep], u, quantile)
    # the share of the patch's measured points that count: at least half, and min_points of the patch
    n_meas = np.bincount(rows, minlength=u)
    enough = (n_pts * (n_points / np.maximum(n_meas, 1)) >= min_points) & (2 * n_pts >= n_meas)
    offset[~enough] = np.nan
    n_far = np.bincount(rows[keep & (d > off_surface_m)], minlength=u)
    off = enough & (offset > off_surface_m) & (n_far >= min_off_points)
    missing = off & (n_faces == 0) & (offset <= near_m)
    only = (n_faces == 0)[rows]
    n_in = np.zeros(u, np.int64)
    if inside_share <= 1 and only.any():
        n_in = np.bincount(rows[only][inside_solid(points[only], vertices, faces)], minlength=u)
    missing |= (n_faces == 0) & (n_in >= min_points) & (n_in >= inside_share * n_meas)
    bad = (off & (n_faces > 0)) | missing
    return Evidence(offset.astype(np.float32), bad, missing)


def weld_by_ids(tris: np.ndarray, vids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A triangle soup as an indexed mesh: corners that share a campus vertex id (and its position) become
    one vertex. tris: (m, 3, 3) float metres; vids: (m, 3) int64 (:mod:`storage.vertex_ids`; -1 and local
    ids never weld). Returns (vertices (v, 3) float64, faces (m, 3) int64): about a sixth of the soup's
    vertices on a welded mesh. Ids that disagree with positions leave the soup as it is.

    >>> t = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[1, 0, 0], [1, 1, 0], [0, 1, 0]]], np.float32)
    >>> v, f = weld_by_ids(t, np.array([[0, 1, 2], [1, 3, 2]]))
    >>> len(v), f.tolist()
    (4, [[0, 1, 2], [1, 3, 2]])
    """
    from storage.vertex_ids import is_campus_id

    corners = tris.reshape(-1, 3)
    ids = vids.reshape(-1)
    key = np.where(is_campus_id(ids), ids, np.iinfo(np.int64).min + np.arange(len(ids)))  # unwelded: unique keys
    _, first, inv = np.unique(key, return_index=True, return_inverse=True)
    vertices = corners[first]
    if not np.array_equal(vertices[inv], corners):  # an id at two positions: trust positions only
        return corners.astype(np.float64), np.arange(len(corners), dtype=np.int64).reshape(-1, 3)
    return vertices.astype(np.float64), inv.reshape(-1, 3).astype(np.int64)


def inside_solid(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, min_votes: int = 4) -> np.ndarray:
    """(n,) bool: points the surface encloses. points: (n, 3) float64; vertices: (v, 3) float64 metres;
    faces: (m, 3) int64.

    Parity of the surface crossings along five rays (+-x, +-y, +z; open3d, float32 around the points'
    centre): odd = inside. A point needs ``min_votes`` odd rays, so one gap in the surface, or a thin
    overhang above a point outside (one crossing straight up), does not make it inside. Orientation-free.

    >>> import trimesh
    >>> box = trimesh.creation.box(extents=(2, 2, 2))                         # a 2 m cube about the origin
    >>> inside_solid(np.array([[0.5, 0.4, 0.3], [1.5, 0.4, 0.3]]), box.vertices, box.faces).tolist()
    [True, False]
    """
    import open3d as o3d

    if not (len(points) and len(faces)):
        return np.zeros(len(points), bool)
    c = points.mean(axis=0)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor((np.asarray(vertices) - c).astype(np.float32)),
                        o3d.core.Tensor(np.asarray(faces).astype(np.uint32)))
    p = (points - c).astype(np.float32)
    votes = np.zeros(len(points), np.int64)
    for d in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0), (0, 0, 1)):
        rays = np.c_[p, np.tile(np.asarray(d, np.float32), (len(p), 1))]
        votes += scene.count_intersections(o3d.core.Tensor(rays)).numpy().astype(np.int64) % 2
    return votes >= min_votes


__all__ = ["MAX_POINTS_PER_PATCH", "Evidence", "inside_solid", "offset_evidence", "range_rows", "strided_ranges", "weld_by_ids"]
