"""The MLS points overlay: the registered points, thinned, as a second 3D Tiles tileset in the mesh's frame.

``output/points/tileset.json`` (refine ADD, the same root ``transform``, ENU -> ECEF, as the mesh tileset)
holds one content ``output/points/{ix}_{iy}.glb`` per ground tile: one glTF ``POINTS`` primitive,
POSITION float32 (glTF y-up ENU metres, the mesh tiles' frame) and COLOR_0 RGBA8 coloured by what the
grader made of the point's patch (``STATUS_COLOURS``: good, bad, unknown because the mesh has no face
there, unknown otherwise). A viewer overlays it on the mesh so a user can judge the registration and the
grades by eye.

The points are the tile stores' (``tiles/*/points.parquet``: registered, campus-local), thinned to about
``budget`` in all: each tile keeps a seeded random subset in proportion to its points (the same subset on
every run). The overlay is rewritten only when a store, its grades, the georeference or the budget
changed (``fingerprints.json`` beside it); with no store it is removed. This module makes the overlay's
content from arrays; :func:`tasks.export.overlay.write_points_overlay` reads the stores and writes it.
"""

from __future__ import annotations

import numpy as np

from tasks.export.content import box_from_bounds
from tasks.export.gltf import ARRAY_BUFFER, FLOAT, UBYTE, _Builder, _pack

POINTS_VERSION = 1
POINTS_BUDGET = 300_000
POINTS_MODE = 0  # glTF primitive mode POINTS
STATUS_NAMES = ("good", "bad", "no face", "unknown")
STATUS_COLOURS = np.array([[0x1B, 0x7A, 0x2E], [0xC6, 0x28, 0x28], [0xD8, 0x1B, 0xB0], [0x26, 0x32, 0x38]], np.uint8)


def thin_indices(n: int, keep: int, seed: int) -> np.ndarray:
    """(min(keep, n),) int64 ascending indices of a seeded random subset of ``range(n)``.

    >>> thin_indices(5, 9, 0).tolist(), len(thin_indices(1000, 10, 3)), bool((thin_indices(50, 5, 1) == thin_indices(50, 5, 1)).all())
    ([0, 1, 2, 3, 4], 10, True)
    """
    if keep >= n:
        return np.arange(n, dtype=np.int64)
    return np.sort(np.random.default_rng(seed).choice(n, keep, replace=False)).astype(np.int64)


def point_status(point_stop: np.ndarray, grade: np.ndarray, n_faces: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(k,) int8 status (index into ``STATUS_NAMES``) of the points ``idx`` (rows of a points table sorted
    by patch), from their patch's grade (u,) int8 and face count (u,); point_stop (u,) int64 is the end
    row of each patch's points (patches in table order).

    >>> point_status(np.array([2, 2, 5, 6]), np.array([0, -1, 1, -1]), np.array([4, 3, 1, 0]), np.array([0, 3, 5])).tolist()
    [0, 1, 2]
    """
    row = np.searchsorted(np.asarray(point_stop), idx, side="right")
    g, nf = np.asarray(grade)[row], np.asarray(n_faces)[row]
    return np.select([g == 0, g == 1, nf == 0], [0, 1, 2], default=3).astype(np.int8)


def build_points_glb(positions: np.ndarray, status: np.ndarray) -> bytes:
    """glb bytes of one POINTS primitive: positions (n, 3) float32 glTF y-up metres, status (n,) int8
    (colour ``STATUS_COLOURS[status]``, stored as linear-light RGBA8 as glTF requires)."""
    from tasks.export.gltf import srgb_to_linear_u8

    b = _Builder()
    n = len(positions)
    pos = np.ascontiguousarray(positions, np.float32)
    colours = srgb_to_linear_u8(STATUS_COLOURS[np.asarray(status, np.int64)])
    attrs = {"POSITION": b.accessor(pos, FLOAT, "VEC3", n, target=ARRAY_BUFFER, minmax=True),
             "COLOR_0": b.accessor(np.ascontiguousarray(colours), UBYTE, "VEC4", n, target=ARRAY_BUFFER,
                                   normalized=True)}
    b.doc.update({"asset": {"version": "2.0", "generator": "ms3d export (points)"}, "scene": 0,
                  "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "mls points"}],
                  "materials": [{"name": "points", "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0},
                                 "extensions": {"KHR_materials_unlit": {}}}],
                  "meshes": [{"name": "mls points", "primitives": [{"attributes": attrs, "material": 0, "mode": POINTS_MODE}]}],
                  "extensionsUsed": ["KHR_materials_unlit"], "buffers": [{"byteLength": b.length}]})  # fmt: skip
    return _pack(b.doc, b.chunks, b.length)


def points_tileset_json(boxes: dict[str, list[float]], transform: list[float]) -> dict:
    """The overlay's tileset: a root (the union of the boxes, no content, refine ADD) over one leaf per
    tile (``{key}.glb``, geometricError 0). boxes: key -> 3D Tiles box (ENU metres, axis-aligned);
    transform: the root's 16 numbers, the mesh tileset's (``GeoRef.tileset_transform()``)."""
    lo = np.min([np.subtract(b[:3], b[3:12:4]) for b in boxes.values()], axis=0)
    hi = np.max([np.add(b[:3], b[3:12:4]) for b in boxes.values()], axis=0)
    diagonal = float(np.linalg.norm(hi - lo))
    root = {"transform": list(transform), "boundingVolume": {"box": box_from_bounds(lo, hi)},
            "geometricError": diagonal, "refine": "ADD",
            "children": [{"boundingVolume": {"box": box}, "geometricError": 0.0, "content": {"uri": f"{k}.glb"}}
                         for k, box in sorted(boxes.items())]}  # fmt: skip
    return {"asset": {"version": "1.1", "generator": f"ms3d export points v{POINTS_VERSION}"},
            "geometricError": diagonal, "root": root}
