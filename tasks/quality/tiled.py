"""Quality tile by tile on the ground grid: memory bounded by one tile, sums merged exactly. Pure."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from storage.ids import TileId
from tasks.geometry.sampling import seed_of
from tasks.quality.metrics import class_names_of, evaluate_partial, validated_mesh
from tasks.quality.stats import QualityPartial, QualityReport


def _faces_by_tile(vertices, faces, tile_size_m: float, pad_m: float) -> dict[TileId, np.ndarray]:
    """Faces whose x/y bounding box, grown by pad_m, touches each tile: {TileId: (k,) int64 sorted}."""
    if len(faces) == 0:
        return {}
    corners = [vertices[faces[:, q], :2] for q in range(3)]
    i0 = np.floor((np.minimum.reduce(corners) - pad_m) / tile_size_m).astype(np.int64)
    i1 = np.floor((np.maximum.reduce(corners) + pad_m) / tile_size_m).astype(np.int64)
    nx, ny = i1[:, 0] - i0[:, 0] + 1, i1[:, 1] - i0[:, 1] + 1
    cnt = nx * ny
    face = np.repeat(np.arange(len(faces)), cnt)
    k = np.arange(len(face)) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    ix, iy = i0[face, 0] + k % nx[face], i0[face, 1] + k // nx[face]
    order = np.lexsort((face, iy, ix))
    ix, iy, face = ix[order], iy[order], face[order]
    cuts = np.flatnonzero((np.diff(ix) != 0) | (np.diff(iy) != 0)) + 1
    return {TileId(int(ix[s]), int(iy[s])): part for s, part in zip(np.r_[0, cuts], np.split(face, cuts))}


def _submesh(vertices, faces, ids):
    used, inv = np.unique(faces[ids], return_inverse=True)
    return vertices[used], inv.reshape(-1, 3)


@dataclass(frozen=True)
class TiledQuality:
    """Exactly aggregated figures of the whole scene and each ground tile's own figures."""

    total: QualityReport
    tiles: Mapping[TileId, QualityReport]


def evaluate_by_tile(pred_vertices, pred_faces, true_vertices, true_faces, *, tile_size_m: float = 100.0,
                     buffer_m: float = 2.0, true_face_mask=None, true_face_class=None, class_names=None,
                     max_distance_m: float | None = None, rng=0, **kwargs) -> TiledQuality:
    """:func:`evaluate_mesh` tile by tile on the ground grid (TileId), memory bounded by one tile.

    Each sample belongs to the tile that contains it; its distance is measured to the other mesh's
    faces within ``buffer_m`` of the tile, which is exact for distances up to buffer_m, so distances
    are capped at buffer_m (and at max_distance_m). Sums are merged, so ``total`` equals
    ``evaluate_mesh(..., max_distance_m=buffer_m)`` (percentiles to the 0.05 mm histogram bin).
    """
    total, tiles = evaluate_tiles(pred_vertices, pred_faces, true_vertices, true_faces, tile_size_m=tile_size_m,
                                  buffer_m=buffer_m, true_face_mask=true_face_mask, true_face_class=true_face_class,
                                  class_names=class_names, max_distance_m=max_distance_m, rng=rng, **kwargs)
    if total is None:
        pv, pf = validated_mesh(pred_vertices, pred_faces, "predicted")
        tv, tf = validated_mesh(true_vertices, true_faces, "truth")
        names = class_names_of(None if true_face_class is None else np.asarray(true_face_class), class_names)
        cap = buffer_m if max_distance_m is None else min(max_distance_m, buffer_m)
        total = evaluate_partial(pv, pf, tv, tf, class_names=names, max_distance_m=cap, rng=seed_of(rng), **kwargs)
    return TiledQuality(total.report(), tiles)


def evaluate_tiles(pred_vertices, pred_faces, true_vertices, true_faces, *, tile_size_m: float = 100.0,
                   buffer_m: float = 2.0, true_face_mask=None, true_face_class=None, class_names=None,
                   max_distance_m: float | None = None, rng=0, part: tuple[int, int] = (0, 1),
                   **kwargs) -> tuple[QualityPartial | None, dict]:
    """The summed partial of the tiles of one share of the scene (``part`` = (k, n): the k-th of n
    interleaved shares of the sorted tiles), and each tile's report; partials of all n shares add up to
    the whole (:func:`evaluate_by_tile`). None when the share holds no tile."""
    pv, pf = validated_mesh(pred_vertices, pred_faces, "predicted")
    tv, tf = validated_mesh(true_vertices, true_faces, "truth")
    tc = None if true_face_class is None else np.asarray(true_face_class, np.int64)
    mask = np.ones(len(tf), bool) if true_face_mask is None else np.asarray(true_face_mask, bool)
    names, seed = class_names_of(tc, class_names), seed_of(rng)
    cap = buffer_m if max_distance_m is None else min(max_distance_m, buffer_m)
    owners = set(_faces_by_tile(pv, pf, tile_size_m, 1e-6)) | set(_faces_by_tile(tv, tf, tile_size_m, 1e-6))
    pred_near = _faces_by_tile(pv, pf, tile_size_m, buffer_m)
    true_near = _faces_by_tile(tv, tf, tile_size_m, buffer_m)
    none = np.zeros(0, np.int64)
    total, tiles = None, {}
    k, n = part
    for tile in sorted(owners)[k::n]:
        pi, ti = pred_near.get(tile, none), true_near.get(tile, none)
        p = evaluate_partial(*_submesh(pv, pf, pi), *_submesh(tv, tf, ti), tile=tile,
                             tile_size_m=tile_size_m,
                             true_face_mask=mask[ti], true_face_class=None if tc is None else tc[ti],
                             class_names=names, max_distance_m=cap, rng=seed, **kwargs)
        if p.accuracy.n[0] or p.completeness.n[0]:
            tiles[tile] = p.report()
        total = p if total is None else total + p
    return total, tiles
