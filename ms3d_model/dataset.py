"""Featurised pairs in memory, the 4:1 split by area, and training batches.

A :class:`PairSet` holds fixed-size features of many pairs (float16 coordinates in the normalised pair
frame, int16 indices: ~18 KB a pair at 256 faces and 512 points), their cues, labels and grid cells.

The split is by **area**, never by pair: the ground is cut into square blocks (``block_m``, world-anchored
through the patch cells), whole blocks go to validation until it holds ``val_fraction`` of a campus's
pairs, and training drops every patch with a neighbour cell (8-neighbourhood in plan, any height) in a
validation block, so no two adjacent patches sit on both sides.
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
         "centre_knn": torch.from_numpy(feats.centre_knn.astype(np.int64))}
    if cues is not None:
        b["cues"] = torch.from_numpy(np.asarray(cues, np.float32))
    return b


def area_split(ijk: np.ndarray, patch_size_m, campus: np.ndarray, block_m: float = 20.0,
               val_fraction: float = 0.2, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Split pairs 4:1 (``val_fraction``) by ground blocks: (train_mask, val_mask), (B,) bool each.

    ijk: (B, 3) int64 patch cells; patch_size_m: (3,) metres; campus: (B,) int campus index (each campus
    is split on its own, so every campus contributes to both sides). Deterministic in ``seed``.
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
    near = np.zeros(len(key), bool)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            near |= np.isin(block_key(ijk[:, 0] + di, ijk[:, 1] + dj), val_blocks)
    return ~near, val


def batches(n: int, batch_size: int, shuffle: bool, rng: np.random.Generator | None = None,
            drop_last: bool = False):
    """Index arrays of consecutive batches over range(n) (shuffled with ``rng`` when asked)."""
    order = rng.permutation(n) if shuffle else np.arange(n)
    stop = n - (n % batch_size) if drop_last else n
    for s in range(0, stop, batch_size):
        yield order[s:s + batch_size]
