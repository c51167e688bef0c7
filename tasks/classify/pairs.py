"""Pairs straight from the patch store: read a tile once, cut it into (mesh patch, point patch) pairs,
featurise them in batches (``ms3d_model.features``, ``ms3d_model.cues``), and cache featurised tiles for
training. Readers take a tile's folder; the campus-wide set is :func:`tasks.classify.stage.campus_pair_set`.

A pair is *gradable* when its patch holds at least ``min_faces`` faces and ``min_points`` points
(``partition.min_faces`` / ``min_points``, default 1): a patch with faces but no points, or points but no
faces, is not a pair the network can grade (see ``tasks.classify.stage`` for the grade it gets).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ms3d_model.context import with_context
from ms3d_model.surface import TileSurface
from ms3d_model.cues import CUE_NAMES, OWN_CUE_NAMES, batch_cues, open_edge_flags
from ms3d_model.dataset import PairSet
from ms3d_model.features import PairFeatures, featurise_pairs
from storage.formats.arrays import read_arrays, write_arrays
from storage.patches.read import PatchStore
from storage.patches.state import store_fingerprint

FACE_COLUMNS = [f"{a}{v}" for v in range(3) for a in "xyz"] + ["vid0", "vid1", "vid2"]
CACHE_VERSION = 4  # 2: pairs above ms3d_model.cues.MAX_SHAPE_POINTS give other cues; 3: order-free subsets;
# 4: point -> mesh cues against the tile's whole surface
CUE_CHUNK = 512  # pairs per batch_cues call (one k-d tree per kind per call)
CUE_POINTS = 3_000_000  # and at most this many points per call (real MLS density: bounded memory)
SPAN_ROWS = 4_000_000  # rows of the points table a streamed reader holds at once


class StorePoints:
    """A tile's points table read by row ranges, never whole (real MLS density: tens of millions of points).

    ``rows(lo, hi)`` -> (hi - lo, 3) float32 metres, campus-local, in patch order."""

    def __init__(self, store: PatchStore):
        self.store = store

    def __len__(self) -> int:
        return self.store.n_points

    def rows(self, lo: int, hi: int) -> np.ndarray:
        return self.store.read_rows_stacked("points", ["x", "y", "z"], lo, hi, np.float32)


def cue_chunks(rows: np.ndarray, max_pairs: int | None = None, max_points: int | None = None) -> list[tuple[int, int]]:
    """Consecutive [s, e) chunks of pairs whose point rows are ``rows`` (P, 2) [start, stop), ascending: at
    most ``max_pairs`` pairs, and the rows they span (gaps included) at most ``max_points`` unless one pair
    alone spans more (defaults: ``CUE_CHUNK`` and ``CUE_POINTS``).

    >>> cue_chunks(np.array([[0, 5], [5, 10], [10, 15], [20, 40], [40, 41]]), max_pairs=3, max_points=12)
    [(0, 2), (2, 3), (3, 4), (4, 5)]
    """
    max_pairs, max_points = max_pairs or CUE_CHUNK, max_points or CUE_POINTS
    out, s = [], 0
    for i, (_, stop) in enumerate(np.asarray(rows, np.int64).tolist()):
        if i > s and (i - s >= max_pairs or stop - int(rows[s][0]) > max_points):
            out.append((s, i))
            s = i
    if s < len(rows):
        out.append((s, len(rows)))
    return out


@dataclass
class TilePairs:
    """A tile's gradable pairs as views into its tables (metres, campus-local).

    keys (P,) int64; ijk (P, 3) int64; rows (P,) int64 row of each pair in the patches table; labels (P,)
    int8 (-1 when the tile has no labels); gradable (U,) bool over all U patches of the tile.
    """

    tile: str
    keys: np.ndarray
    ijk: np.ndarray
    rows: np.ndarray
    labels: np.ndarray
    gradable: np.ndarray
    patch_size_m: tuple[float, float, float]
    _pts: np.ndarray
    _tris: np.ndarray
    _vids: np.ndarray
    _open: np.ndarray
    _pr: np.ndarray
    _fr: np.ndarray
    _cues: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.keys)

    @property
    def all_points(self) -> np.ndarray:
        """(n, 3) float32 every point of the tile, in patch order (metres, campus-local); read whole when
        the tile was opened with ``stream_points`` (prefer :meth:`points_at`)."""
        return self._pts if isinstance(self._pts, np.ndarray) else self._pts.rows(0, len(self._pts))

    def points_at(self, rows: np.ndarray) -> np.ndarray:
        """(q, 3) float32 the points at ascending ``rows`` (q,) of the points table, read ``SPAN_ROWS`` rows
        at a time when streamed."""
        rows = np.asarray(rows, np.int64)
        if isinstance(self._pts, np.ndarray):
            return self._pts[rows]
        out = np.empty((len(rows), 3), np.float32)
        for lo in range(0, len(self._pts), SPAN_ROWS):
            a, b = np.searchsorted(rows, [lo, lo + SPAN_ROWS])
            if b > a:
                span = self._pts.rows(int(rows[a]), int(rows[b - 1]) + 1)
                out[a:b] = span[rows[a:b] - rows[a]]
        return out

    @property
    def all_triangles(self) -> np.ndarray:
        """(m, 3, 3) float32 every face of the tile, in patch order."""
        return self._tris

    @property
    def all_vids(self) -> np.ndarray:
        """(m, 3) int64 campus vertex ids of every face's corners (:mod:`storage.vertex_ids`)."""
        return self._vids

    def cues(self, seed: int) -> np.ndarray:
        """(P, N_CUES) float32 cues of every pair of the tile: each pair's own, then its neighbourhood in the
        tile (:mod:`ms3d_model.context`). Computed once per seed."""
        if seed not in self._cues:
            surface = TileSurface.from_triangles(self._tris) if len(self._tris) and len(self) else None
            own = [batch_cues(*self.raw_cue_inputs(np.arange(s, e)), seed=seed, surface=surface)
                   for s, e in cue_chunks(self._pr)]
            own = np.concatenate(own) if own else np.zeros((0, len(OWN_CUE_NAMES)), np.float32)
            self._cues[seed] = with_context(own, self.ijk)
        return self._cues[seed]

    def raw_cue_inputs(self, idx) -> tuple[list, list, list, np.ndarray]:
        """(points, tris, open_edges, keys) of the pairs ``idx``: the arguments of ``batch_cues``."""
        pts, tris, _, open_edges = self.raw(idx)
        return pts, tris, open_edges, self.keys[idx]

    def raw(self, idx) -> tuple[list, list, list, list]:
        """(points, tris, vids, open_edges) lists of the pairs ``idx`` (streamed: one read of their span)."""
        idx = np.asarray(idx, np.int64)
        span, lo = self._pts, 0
        if not isinstance(span, np.ndarray) and len(idx):
            lo = int(self._pr[idx, 0].min())
            span = span.rows(lo, int(self._pr[idx, 1].max()))
        pts = [span[self._pr[i, 0] - lo:self._pr[i, 1] - lo] for i in idx]
        sl = [slice(self._fr[i, 0], self._fr[i, 1]) for i in idx]
        return pts, [self._tris[s] for s in sl], [self._vids[s] for s in sl], [self._open[s] for s in sl]


def gradable_mask(patches: dict, min_faces: int = 1, min_points: int = 1) -> np.ndarray:
    """(U,) bool: which patches of a patches table hold a gradable pair (at least one face and point)."""
    return (patches["n_faces"] >= max(min_faces, 1)) & (patches["n_points"] >= max(min_points, 1))


def read_tile_pairs(tile_dir: str | Path, min_faces: int = 1, min_points: int = 1,
                    stream_points: bool = False) -> TilePairs:
    """Read a tile's points and faces once and index its gradable pairs. ``stream_points``: leave the points
    in the store and read them by row ranges when needed (memory bounded whatever the MLS density; the faces
    are read whole: they do not grow with the scan)."""
    store = PatchStore(tile_dir)
    p = store.patches()
    gradable = gradable_mask(p, min_faces, min_points)
    rows = np.flatnonzero(gradable)
    lab = store.side("labels")
    labels = (lab["label"][rows].astype(np.int8) if lab is not None else np.full(len(rows), -1, np.int8))
    pts = StorePoints(store) if stream_points else store.read_all_stacked("points", ["x", "y", "z"], np.float32)
    tris = store.read_all_stacked("faces", FACE_COLUMNS[:9], np.float32).reshape(-1, 3, 3)
    vids = store.read_all_stacked("faces", FACE_COLUMNS[9:], np.int64)
    open_edges = open_edge_flags(vids) if len(vids) else np.zeros((0, 3), bool)
    pr = np.stack([p["point_start"][rows], p["point_stop"][rows]], axis=1)
    fr = np.stack([p["face_start"][rows], p["face_stop"][rows]], axis=1)
    ijk = np.stack([p["i"][rows], p["j"][rows], p["k"][rows]], axis=1)
    return TilePairs(store.meta.tile, p["patch"][rows], ijk, rows, labels, gradable, store.meta.patch_size_m,
                     pts, tris, vids, open_edges, pr, fr)


def featurise_tile_pairs(tp: TilePairs, idx: np.ndarray, max_points: int, max_faces: int, k_centre: int,
                         seed: int, with_cues: bool = True, with_feats: bool = True) -> tuple[PairFeatures | None, np.ndarray]:
    """Features (None unless ``with_feats``) and cues ((B, N_CUES) float32, :meth:`TilePairs.cues`; zeros
    unless ``with_cues``) of the pairs ``idx`` of a tile."""
    idx = np.asarray(idx, np.int64)
    feats = None
    if with_feats:
        pts, tris, vids, _ = tp.raw(idx)
        feats = featurise_pairs(pts, tris, vids, tp.keys[idx], max_points, max_faces, k_centre, seed)
    cues = tp.cues(seed)[idx] if with_cues else np.zeros((len(idx), len(CUE_NAMES)), np.float32)
    return feats, cues


def iter_tile_batches(tp: TilePairs, batch_size: int, max_points: int, max_faces: int, k_centre: int,
                      seed: int = 0, with_cues: bool = True,
                      with_feats: bool = True) -> Iterator[tuple[np.ndarray, PairFeatures | None, np.ndarray]]:
    """(pair indices, features, cues) of consecutive batches of a tile's pairs."""
    for s in range(0, len(tp), batch_size):
        idx = np.arange(s, min(s + batch_size, len(tp)))
        feats, cues = featurise_tile_pairs(tp, idx, max_points, max_faces, k_centre, seed, with_cues, with_feats)
        yield idx, feats, cues


def _cache_name(cache_dir, campus_name: str, tile: str, kind: str, spec: dict) -> Path | None:
    if not cache_dir:
        return None
    h = hashlib.sha256(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
    return Path(cache_dir) / f"{campus_name}_{tile}_{kind}_{h}.npz"


def tile_pair_set(tile_dir: str | Path, campus_name: str, max_points: int, max_faces: int, k_centre: int,
                  seed: int, cache_dir: str | Path | None = None, min_faces: int = 1, min_points: int = 1,
                  chunk: int = 256, labelled_only: bool = True, max_pairs: int | None = None) -> PairSet:
    """All gradable (labelled) pairs of a tile, featurised. With ``cache_dir``, features (per input size) and
    cues (per tile) are cached as .npz, keyed by the tile's store fingerprint and the parameters.
    ``max_pairs``: keep a seeded random subset of at most this many pairs (large input sizes)."""
    tile_dir = Path(tile_dir)
    base = {"v": CACHE_VERSION, "tile": store_fingerprint(tile_dir, sides=("labels",)), "seed": seed, "min": [min_faces, min_points],
            "labelled_only": labelled_only} | ({"max_pairs": max_pairs} if max_pairs else {})
    f_path = _cache_name(cache_dir, campus_name, tile_dir.name, "feats",
                         base | {"max_points": max_points, "max_faces": max_faces, "k": k_centre})
    c_path = _cache_name(cache_dir, campus_name, tile_dir.name, "cues", base | {"cues": list(CUE_NAMES)})
    f_ok, c_ok = (f_path is not None and f_path.exists()), (c_path is not None and c_path.exists())
    if f_ok and c_ok:
        return PairSet.from_arrays({**read_arrays(f_path), "cues": read_arrays(c_path)["cues"]})
    tp = read_tile_pairs(tile_dir, min_faces, min_points)
    keep = np.flatnonzero(tp.labels >= 0) if labelled_only else np.arange(len(tp))
    if max_pairs is not None and len(keep) > max_pairs:
        keep = np.sort(np.random.default_rng(seed).choice(keep, max_pairs, replace=False))
    if f_ok:  # features cached, cues new (a new cue set): cues only, the tile's pairs in the cached order
        ps = PairSet.from_arrays({**read_arrays(f_path), "cues": tp.cues(seed)[keep]})
        write_arrays(c_path, {"cues": ps.cues})
        return ps
    parts = []
    for s in range(0, len(keep), chunk):
        idx = keep[s:s + chunk]
        f, c = featurise_tile_pairs(tp, idx, max_points, max_faces, k_centre, seed)
        parts.append(PairSet(f, c, tp.labels[idx], tp.ijk[idx], np.zeros(len(idx), np.int16), (campus_name,)).compact())
    ps = PairSet.concat(parts) if parts else empty_pair_set(max_points, max_faces, k_centre, campus_name)
    if f_path is not None:
        arrays = ps.to_arrays()
        write_arrays(c_path, {"cues": arrays.pop("cues")})
        write_arrays(f_path, arrays | {"cues": np.zeros((len(ps), 0), np.float32)})
    return ps


def empty_pair_set(n: int, f: int, k: int, name: str) -> PairSet:
    """A PairSet of no pairs with feature shapes (n points, f faces, k neighbours) of campus ``name``."""
    z = np.zeros
    feats = PairFeatures(z((0, n, 3), np.float16), z((0, f, 3), np.float16), z((0, f, 3), np.float16),
                         z((0, f, 18), np.float16), z((0, f, 3), np.int16), z((0, f, k), np.int16),
                         z(0, np.int64), z(0, np.int64), z(0, np.float32), z(0, np.int64))
    return PairSet(feats, z((0, len(CUE_NAMES)), np.float32), z(0, np.int8), z((0, 3), np.int64), z(0, np.int16), (name,))
