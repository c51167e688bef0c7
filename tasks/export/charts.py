"""Box-projection charts: a texture parameterisation for baking that scales to decimated city meshes.

Each face is classed by the axis (+E, -E, +N, -N, +U, -U) nearest its normal smoothed over its neighbours
(so a noisy wall stays one class); faces of one class that share an edge form a chart; a chart is
projected orthographically on its axis plane (a surface whose normals all lie within 54.7 deg of one axis
is a graph over that plane, so nothing folds; texels stretch by at most 1 / cos 54.7 deg = 1.73); charts
of a few faces are absorbed by a neighbouring chart when they still face its axis. The charts' boxes are
packed in shelves (tallest first) at one common texel size, shrunk until they fit the square atlas. What
stays a chart of fewer than ``MIN_CHART_FACES`` faces (slivers and folds of a decimated noisy surface:
~12 % of the faces, in ~95 % of the charts, on a decimated demo tile) gets one texel, no padding: its
colour is painted once (:func:`tasks.export.bake.bake_lod`), as a vertex colour would be.

Measured here on a decimated demo tile (473 k faces): ~4 s, against 4+ minutes for xatlas on 50 k faces
of a noisy surface (its chart growing does not scale to decimated photogrammetry).
"""

from __future__ import annotations

import numpy as np

MIN_CHART_FACES = 6  # charts with fewer faces are absorbed by a neighbour when they can be
ABSORB_MIN_COS = 0.2  # a face joins a neighbour's chart only if its normal has at least this along the chart's axis
SMOOTH_ROUNDS = 2


def face_normals(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3) float64 area-weighted face normals (length = 2 x area) of positions (n, 3), faces (m, 3)."""
    p = positions.astype(np.float64)
    return np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])


def _smoothed(normals: np.ndarray, faces: np.ndarray, n_vertices: int, rounds: int) -> np.ndarray:
    """Face normals averaged over the faces sharing a vertex, ``rounds`` times."""
    fn = normals
    for _ in range(rounds):
        vn = np.zeros((n_vertices, 3))
        for k in range(3):
            for c in range(3):
                vn[:, c] += np.bincount(faces[:, k], fn[:, c], n_vertices)
        fn = vn[faces[:, 0]] + vn[faces[:, 1]] + vn[faces[:, 2]]
    return fn


def axis_class(normals: np.ndarray) -> np.ndarray:
    """(m,) int8 in 0..5: 2 x (axis of the largest |component|) + (1 if that component is negative).

    >>> axis_class(np.array([[0.1, -2.0, 0.3], [0, 0, 1.0]])).tolist()
    [3, 4]
    """
    a = np.argmax(np.abs(normals), axis=1)
    return (2 * a + (normals[np.arange(len(normals)), a] < 0)).astype(np.int8)


def _along(normals: np.ndarray, cls: np.ndarray) -> np.ndarray:
    """(m,) the unit normals' component along their class's axis direction."""
    unit = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-30)
    sign = np.where(cls % 2 == 1, -1.0, 1.0)
    return unit[np.arange(len(unit)), cls // 2] * sign


def edge_pairs(faces: np.ndarray) -> np.ndarray:
    """(k, 2) int64 pairs of faces sharing an edge (an edge of three or more faces chains them)."""
    m = len(faces)
    e = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64), axis=1)
    key = e[:, 0] * (int(faces.max()) + 1 if m else 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    same = key[order][1:] == key[order][:-1]
    face_of = np.repeat(np.arange(m), 3)[order]
    return np.stack([face_of[:-1][same], face_of[1:][same]], axis=1)


def _components(m: int, pairs: np.ndarray, cls: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    keep = pairs[cls[pairs[:, 0]] == cls[pairs[:, 1]]]
    graph = coo_matrix((np.ones(len(keep), np.int8), (keep[:, 0], keep[:, 1])), shape=(m, m))
    return connected_components(graph, directed=False)[1]


def chart_faces(positions: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(chart of each face (m,) int64 in 0..c-1, axis class of each chart (c,) int8)."""
    m = len(faces)
    own = face_normals(positions, faces)
    cls = axis_class(_smoothed(own, faces, len(positions), SMOOTH_ROUNDS))
    flipped = _along(own, cls) <= 0  # a face turned away from its smoothed class projects folded: its own class
    cls[flipped] = axis_class(own[flipped])
    pairs = edge_pairs(faces)
    both = np.concatenate([pairs, pairs[:, ::-1]])
    label = _components(m, pairs, cls)
    for _ in range(3):
        size = np.bincount(label)
        tiny = size[label] < MIN_CHART_FACES
        cand = both[tiny[both[:, 0]] & ~tiny[both[:, 1]]]  # (tiny face, face of a chart that stays)
        if not len(cand):
            break
        ok = _along(own[cand[:, 0]], cls[cand[:, 1]]) > ABSORB_MIN_COS
        cand = cand[ok]
        cls[cand[:, 0]] = cls[cand[:, 1]]
        label = _components(m, pairs, cls)
    _, label = np.unique(label, return_inverse=True)
    chart_cls = np.zeros(label.max() + 1 if m else 0, np.int8)
    chart_cls[label] = cls
    return label.astype(np.int64), chart_cls


def shelf_pack(sizes: np.ndarray, width: int) -> tuple[np.ndarray, int]:
    """Rectangles (c, 2) int (w, h) in shelves of ``width``, tallest first. Returns (offsets (c, 2) int64 of
    each rectangle's corner, height used).

    >>> off, h = shelf_pack(np.array([[3, 1], [2, 2], [2, 2]]), 4)
    >>> off.tolist(), h
    ([[0, 2], [0, 0], [2, 0]], 3)
    """
    order = np.lexsort((-sizes[:, 0], -sizes[:, 1]))
    off = np.zeros((len(sizes), 2), np.int64)
    x = y = shelf = 0
    for i in order.tolist():
        w, h = int(sizes[i, 0]), int(sizes[i, 1])
        if x + w > width and x > 0:
            x, y, shelf = 0, y + shelf, 0
        off[i] = (x, y)
        x, shelf = x + w, max(shelf, h)
    return off, y + shelf


def parameterize(positions: np.ndarray, faces: np.ndarray, px: int, padding: int = 2
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Charts of the mesh packed in one ``px`` square atlas. positions: (n, 3) metres; faces: (m, 3).
    Returns (vmap (n',) int64: the input vertex of each output vertex (split at chart borders), faces
    (m, 3) int32 over the output vertices, same order, uv (n', 2) float32 in [0, 1])."""
    m, n = len(faces), len(positions)
    label, chart_cls = chart_faces(positions, faces)
    key = label[:, None] * n + faces.astype(np.int64)  # (chart, vertex): one output vertex each
    uniq, inverse = np.unique(key.reshape(-1), return_inverse=True)
    vmap, chart = uniq % n, uniq // n
    axis = chart_cls[chart] // 2
    keep = np.array([[1, 2], [0, 2], [0, 1]])[axis]  # the two other axes
    p = positions[vmap].astype(np.float64)
    plane = np.take_along_axis(p, keep, axis=1)  # (n', 2) metres in the chart's projection plane
    c = len(chart_cls)
    lo = np.full((c, 2), np.inf)
    hi = np.full((c, 2), -np.inf)
    np.minimum.at(lo, chart, plane)
    np.maximum.at(hi, chart, plane)
    ext = hi - lo
    point = np.bincount(label, minlength=c) < MIN_CHART_FACES  # one texel each
    ext[point] = 0.0
    budget = 0.7 * px * px - point.sum()
    scale = np.sqrt(max(budget, 1.0) / max(float((ext[:, 0] * ext[:, 1]).sum()), 1e-12))  # texels per metre
    for _ in range(40):
        sizes = np.ceil(ext * scale).astype(np.int64) + 1 + 2 * padding
        sizes[point] = 1
        if sizes.max() <= px:
            off, used = shelf_pack(sizes, px)
            if used <= px:
                break
            scale *= min(0.97, np.sqrt(px / used))
        else:
            scale *= 0.97 * (px - 1 - 2 * padding) / (sizes.max() - 1 - 2 * padding)
    on_point = point[chart][:, None]  # a one-texel chart's vertices all sit at its texel's centre
    texel = off[chart] + 0.5 + np.where(on_point, 0.0, padding + (plane - lo[chart]) * scale)
    uv = (texel / px).astype(np.float32)
    return vmap.astype(np.int64), inverse.reshape(m, 3).astype(np.int32), uv
