"""Featurised pairs in memory, the 4:1 split by area, and training batches.

A :class:`PairSet` holds fixed-size features of many pairs (float16 coordinates in the normalised pair
frame, int16 indices: ~18 KB a pair at 256 faces and 512 points), their cues, labels and grid cells.

The split is by **area**, never by pair: the ground is cut into square blocks (``block_m``, world-anchored
through the patch cells), whole blocks go to validation until it holds ``val_fraction`` of a campus's
pairs, and training drops every pair within ``buffer_m`` (plan distance, beyond touching) of a validation
pair, so no defect sits on both sides: the buffer defaults to the plan extent of the largest connected bad
region (:func:`largest_defect_extent_m`), not one patch.

:class:`PairTensors` is a featurised set held as torch tensors once (compact dtypes), so training draws
batches by indexing instead of converting arrays every step; :func:`save_pair_set` / :func:`load_pair_set`
cache a whole featurised set as one ``.npz`` (training keys it by its inputs: ``flows.train.load_pairs``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np
import torch

from .features import PairFeatures

_F16 = ("points", "centres", "normals", "corners")
_I16 = ("face_nbr", "centre_knn")


@dataclass
class PairSet:
    """Pairs ready for a network. feats: PairFeatures (stored compact); cues (B, C) float32; labels (B,) int8
    (-1 unknown); ijk (B, 3) int64 patch cells; campus (B,) int16 index into ``names``."""

    feats: PairFeatures
    cues: np.ndarray
    labels: np.ndarray
    ijk: np.ndarray
    campus: np.ndarray
    names: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.labels)

    def take(self, idx) -> PairSet:
        return PairSet(self.feats.take(idx), self.cues[idx], self.labels[idx], self.ijk[idx], self.campus[idx],
                       self.names)

    @staticmethod
    def concat(parts: list[PairSet]) -> PairSet:
        names: list[str] = []
        campus = []
        for p in parts:
            remap = np.array([_index(names, n) for n in p.names] or [0], np.int16)
            campus.append(remap[p.campus])
        return PairSet(PairFeatures.concat([p.feats for p in parts]), np.concatenate([p.cues for p in parts]),
                       np.concatenate([p.labels for p in parts]), np.concatenate([p.ijk for p in parts]),
                       np.concatenate(campus), tuple(names))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Flat dict for ``np.savez`` (compact dtypes)."""
        out = {f"f_{f.name}": _compact(f.name, getattr(self.feats, f.name)) for f in fields(PairFeatures)}
        return out | {"cues": self.cues, "labels": self.labels, "ijk": self.ijk, "campus": self.campus,
                      "names": np.array(self.names)}

    @staticmethod
    def from_arrays(d) -> PairSet:
        feats = PairFeatures(**{f.name: d[f"f_{f.name}"] for f in fields(PairFeatures)})
        return PairSet(feats, d["cues"], d["labels"], d["ijk"], d["campus"], tuple(str(n) for n in d["names"]))

    def compact(self) -> PairSet:
        feats = PairFeatures(**{f.name: _compact(f.name, getattr(self.feats, f.name)) for f in fields(PairFeatures)})
        return PairSet(feats, self.cues, self.labels, self.ijk, self.campus, self.names)


def _index(names: list[str], n: str) -> int:
    if n not in names:
        names.append(n)
    return names.index(n)


def _compact(name: str, a: np.ndarray) -> np.ndarray:
    if name in _F16:
        return a.astype(np.float16)
    if name in _I16:
        return a.astype(np.int16)
    return a


def to_batch(feats: PairFeatures | None, cues: np.ndarray | None = None, noise_m: float = 0.0,
             rng: np.random.Generator | None = None) -> dict[str, torch.Tensor]:
    """Network input tensors of the pairs in ``feats`` (float32, int64); only ``cues`` when feats is None.

    noise_m: standard deviation (metres) of Gaussian noise added to the points (§4.1.2's augmentation;
    converted to pair units by each pair's scale, clipped at 3 sigma); 0 for evaluation.
    """
    if feats is None:
        return {"cues": torch.from_numpy(np.asarray(cues, np.float32))}
    pts = feats.points.astype(np.float32)
    if noise_m > 0:
        rng = rng or np.random.default_rng()
        s = (noise_m / feats.scale.astype(np.float32))[:, None, None]
        pts = pts + np.clip(rng.standard_normal(pts.shape, dtype=np.float32), -3, 3) * s
    b = {"points": torch.from_numpy(pts),
         "centres": torch.from_numpy(feats.centres.astype(np.float32)),
         "normals": torch.from_numpy(feats.normals.astype(np.float32)),
         "corners": torch.from_numpy(feats.corners.astype(np.float32)),
         "face_nbr": torch.from_numpy(feats.face_nbr.astype(np.int64)),
         "centre_knn": torch.from_numpy(feats.centre_knn.astype(np.int64)),
         "scale": torch.from_numpy(feats.scale.astype(np.float32)),
         "n_points": torch.from_numpy(feats.n_points.astype(np.float32)),
         "n_faces": torch.from_numpy(feats.n_faces.astype(np.float32))}
    if cues is not None:
        b["cues"] = torch.from_numpy(np.asarray(cues, np.float32))
    return b


def area_split(ijk: np.ndarray, patch_size_m, campus: np.ndarray, block_m: float = 20.0,
               val_fraction: float = 0.2, seed: int = 0, buffer_m: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Split pairs 4:1 (``val_fraction``) by ground blocks: (train_mask, val_mask), (B,) bool each.

    ijk: (B, 3) int64 patch cells; patch_size_m: (3,) metres; campus: (B,) int campus index (each campus
    is split on its own, so every campus contributes to both sides). Deterministic in ``seed``.
    buffer_m: a pair outside validation is dropped (in neither mask) when its cell's plan centre lies within
    ``buffer_m`` + one cell diagonal of a validation cell's (0: only cells touching a validation cell,
    diagonals included).
    """
    ijk = np.asarray(ijk, np.int64)
    sx, sy = float(patch_size_m[0]), float(patch_size_m[1])
    campus = np.asarray(campus, np.int64)

    def block_key(i, j):
        bx = np.floor(i * sx / block_m).astype(np.int64)
        by = np.floor(j * sy / block_m).astype(np.int64)
        return (campus << 48) ^ ((bx & 0xFFFFFF) << 24) ^ (by & 0xFFFFFF)

    key = block_key(ijk[:, 0], ijk[:, 1])
    val_blocks = []
    rng = np.random.default_rng(seed)
    for c in np.unique(campus):
        blocks, counts = np.unique(key[campus == c], return_counts=True)
        order = rng.permutation(len(blocks))
        cum = np.cumsum(counts[order])
        n_val = int(np.searchsorted(cum, val_fraction * cum[-1])) + 1
        val_blocks.append(blocks[order[:n_val]])
    val_blocks = np.concatenate(val_blocks) if val_blocks else np.zeros(0, np.int64)
    val = np.isin(key, val_blocks)
    return ~val & ~_near_validation(ijk, (sx, sy), campus, val, buffer_m), val


def _near_validation(ijk: np.ndarray, size_xy, campus: np.ndarray, val: np.ndarray, buffer_m: float) -> np.ndarray:
    """(B,) bool: the cell's plan centre is within buffer_m + one cell diagonal of a validation cell's."""
    from scipy.spatial import cKDTree

    xy = (ijk[:, :2] + 0.5) * np.asarray(size_xy, np.float64)
    reach = float(buffer_m) + float(np.hypot(*size_xy)) * (1 + 1e-9)
    near = np.zeros(len(ijk), bool)
    for c in np.unique(campus):
        here, vmask = campus == c, (campus == c) & val
        if vmask.any():
            d, _ = cKDTree(xy[vmask]).query(xy[here], distance_upper_bound=reach)
            near[here] = np.isfinite(d)
    return near


def largest_defect_extent_m(ijk: np.ndarray, labels: np.ndarray, patch_size_m, campus: np.ndarray | None = None,
                            cap_m: float | None = None) -> float:
    """Plan extent (metres) of the largest connected set of bad cells (26-neighbourhood), over all campuses:
    max over components of max(x span, y span) of the cells' footprints. 0 without bad pairs; at most
    ``cap_m`` when given (defects along a facade can touch and join into one long component).

    >>> ijk = np.array([[0, 0, 0], [1, 0, 0], [2, 1, 1], [9, 9, 0]]); round(largest_defect_extent_m(ijk, np.array([1, 1, 1, 1]), (2.3, 1.0, 0.7)), 2)
    6.9
    """
    from scipy import ndimage

    ijk = np.asarray(ijk, np.int64)
    bad = np.asarray(labels) == 1
    campus = np.zeros(len(ijk), np.int64) if campus is None else np.asarray(campus, np.int64)
    best = 0.0
    for c in np.unique(campus[bad]):
        cells = ijk[bad & (campus == c)]
        lo = cells.min(0)
        grid = np.zeros(cells.max(0) - lo + 1, bool)
        grid[tuple((cells - lo).T)] = True
        lab, n = ndimage.label(grid, structure=np.ones((3, 3, 3), bool))
        for sl in ndimage.find_objects(lab):
            span = max((sl[0].stop - sl[0].start) * float(patch_size_m[0]), (sl[1].stop - sl[1].start) * float(patch_size_m[1]))
            best = max(best, span)
    return min(best, cap_m) if cap_m is not None else best


@dataclass
class PairTensors:
    """A :class:`PairSet`'s network inputs as torch tensors, converted once (float16 / int16 as stored):
    points (B, N, 3), centres / normals (B, F, 3), corners (B, F, 18), face_nbr (B, F, 3), centre_knn
    (B, F, K), scale (B,) float32 metres per pair unit, n_points / n_faces (B,) float32 counts, cues (B, C) float32, labels (B,) int64."""

    tensors: dict[str, torch.Tensor]

    @staticmethod
    def from_pairs(ps: PairSet) -> PairTensors:
        t = {name: torch.from_numpy(np.ascontiguousarray(_compact(name, getattr(ps.feats, name))))
             for name in _F16 + _I16}
        t["scale"] = torch.from_numpy(np.asarray(ps.feats.scale, np.float32))
        for name in ("n_points", "n_faces"):
            t[name] = torch.from_numpy(np.asarray(getattr(ps.feats, name), np.float32))
        t["cues"] = torch.from_numpy(np.asarray(ps.cues, np.float32))
        t["labels"] = torch.from_numpy(np.asarray(ps.labels, np.int64))
        return PairTensors(t)

    def __len__(self) -> int:
        return len(self.tensors["labels"])

    def batch(self, idx, with_cues: bool = False, noise_m: float = 0.0,
              generator: torch.Generator | None = None) -> dict[str, torch.Tensor]:
        """Network inputs of pairs ``idx`` (float32 / int64), as :func:`to_batch` makes them."""
        idx = torch.as_tensor(np.asarray(idx), dtype=torch.int64)
        t = self.tensors
        pts = t["points"].index_select(0, idx).float()
        if noise_m > 0:
            s = (noise_m / t["scale"].index_select(0, idx))[:, None, None]
            pts = pts + torch.randn(pts.shape, generator=generator).clamp_(-3, 3) * s
        b = {"points": pts}
        for name in ("centres", "normals", "corners"):
            b[name] = t[name].index_select(0, idx).float()
        for name in _I16:
            b[name] = t[name].index_select(0, idx).long()
        for name in ("scale", "n_points", "n_faces"):
            b[name] = t[name].index_select(0, idx)
        if with_cues:
            b["cues"] = t["cues"].index_select(0, idx)
        return b


def save_pair_set(ps: PairSet, path) -> None:
    """Write a featurised set to ``path`` (.npz, compact dtypes) atomically (a temporary name, then rename)."""
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp.npz")
    np.savez(tmp, **ps.to_arrays())
    tmp.replace(path)


def load_pair_set(path) -> PairSet:
    with np.load(path, allow_pickle=False) as d:
        return PairSet.from_arrays({k: d[k] for k in d.files})


def batches(n: int, batch_size: int, shuffle: bool, rng: np.random.Generator | None = None,
            drop_last: bool = False):
    """Index arrays of consecutive batches over range(n) (shuffled with ``rng`` when asked)."""
    order = rng.permutation(n) if shuffle else np.arange(n)
    stop = n - (n % batch_size) if drop_last else n
    for s in range(0, stop, batch_size):
        yield order[s:s + batch_size]
