"""Which MLS points are held out of the repair, to measure the models on points that shaped neither of them.

Real users have no truth, only their scan: a share of the scan kept out of the fusion and meshing is the
next best thing. Held-out points are whole strips of the scan, never scattered points (a scattered
tenth leaves every neighbour of a held-out point in the fusion, so the model would still be fitted to
it): a strip is a block of ``block_s`` GPS seconds (9 m of track at 9 m/s for 1 s; the passes of a road,
driven at different times, fall in different blocks). Points that carry no time (``gps_time`` 0: a PLY or
XYZ input) fall in strips of ``cell_m`` ground cells of world coordinates instead.

The choice is a function of the strip's id alone: strip ``b`` is held out when ``frac(b / phi + offset(seed))``
is below ``share`` (a Weyl sequence: any run of consecutive strips holds out ``share`` of them to within a
few strips, spread evenly along the drive, where a hash left a short scan of ten strips with a third of them
held out). So it depends on the points alone: the same points in any order, tile or region, read by any
stage, give the same choice, and nothing has to be stored to repeat it (the counts are recorded by the
stages that use it: ``report/holdout.json``, the regions' ``mls_held_out``). One rule keeps small data working: a patch never
loses all its points (where every point of a patch is in held-out strips, that patch keeps them), so
no tile is ever held out whole and no patch the grader graded is left without points for the repair.

Which stages use it (the honest choice: held-out points shape nothing of the output mesh's geometry):

- the repair's fusion and meshing read the region's points without the held-out ones
  (``tasks.repair``), the rebuilt faces are made from the other points;
- the grader (``tasks.classify``) grades with every point: the grades, so the regions, stay those of a
  run without a holdout (turning it on or off redoes no grading), and a patch's points are too few to
  lose a tenth of in a 2.3 x 1.0 x 0.7 m cell. The price: a held-out strip helped decide *where* to
  rebuild (not *what*), so the merged model's figures on held-out points are optimistic where the grader
  acted on the held-out strip alone; where the kept points of the same patch agree with it, as they do
  on a surface both passes scanned, the choice is the same without it;
- texturing's occlusion test (which voxels the MLS saw) uses every point: it chooses colours, not shape;
- the quality stage measures the held-out points' distances to the input mesh and to the merged model.

    >>> import numpy as np
    >>> h = Holdout(share=0.5, block_s=1.0, cell_m=5.0, seed=3)
    >>> t = np.repeat(np.arange(6, dtype=float), 2) + 100.25  # six one-second strips of two points
    >>> m = h.mask(t, np.zeros((12, 2)), patch=np.arange(12) // 4)
    >>> m.reshape(-1, 2).all(1).tolist() == m.reshape(-1, 2).any(1).tolist()  # strips are held out whole
    True
    >>> Holdout(share=0.0).mask(t, np.zeros((12, 2))).any(), Holdout(share=0.99).mask(t, np.zeros((12, 2))).all()
    (np.False_, np.False_)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ms3d_model.hashing import splitmix64

_TIMELESS = np.int64(1) << np.int64(62)  # strip ids of ground cells: apart from every time block's
_GOLDEN = np.uint64(0x9E3779B97F4A7C15)  # 2**64 / golden ratio: the Weyl sequence's step


@dataclass(frozen=True)
class Holdout:
    """The strip choice: ``share`` in [0, 1) of the strips (0: none), strips of ``block_s`` GPS seconds
    (``cell_m`` world ground cells where a point has no time), chosen by ``seed``."""

    share: float = 0.1
    block_s: float = 1.0
    cell_m: float = 5.0
    seed: int = 0

    @property
    def enabled(self) -> bool:
        return self.share > 0

    def to_json(self) -> dict:
        return {"share": float(self.share), "block_s": float(self.block_s), "cell_m": float(self.cell_m),
                "seed": int(self.seed), "rule": "weyl sequence over gps-time strips, ground cells without time; no patch emptied"}

    def strip_ids(self, gps_time: np.ndarray, xy_world: np.ndarray) -> np.ndarray:
        """(n,) int64 strip id of each point: its GPS-time block, or its ground cell where gps_time is 0.
        gps_time: (n,) float64 seconds; xy_world: (n, 2) float64 world metres (only used without a time)."""
        t = np.asarray(gps_time, np.float64)
        ids = np.floor(t / self.block_s).astype(np.int64)
        timeless = t == 0
        if timeless.any():
            c = np.floor(np.asarray(xy_world, np.float64)[timeless] / self.cell_m).astype(np.int64)
            ids[timeless] = _TIMELESS | ((c[:, 0] & 0xFFFFFFF) << 28) | (c[:, 1] & 0xFFFFFFF)
        return ids

    def held_strips(self, strip_ids: np.ndarray) -> np.ndarray:
        """(n,) bool: whether each strip id is held out (a seeded hash below ``share``)."""
        if not self.enabled:
            return np.zeros(len(strip_ids), bool)
        offset = splitmix64(np.array([self.seed % 2**64], np.uint64))[0]
        with np.errstate(over="ignore"):  # uint64 wrapping arithmetic is the point
            u = np.asarray(strip_ids, np.int64).view(np.uint64) * _GOLDEN + offset
        return (u >> np.uint64(11)).astype(np.float64) * 2.0**-53 < self.share

    def mask(self, gps_time: np.ndarray, xy_world: np.ndarray, patch: np.ndarray | None = None) -> np.ndarray:
        """(n,) bool: the held-out points among ``n`` (see the module doc). patch: (n,) int64 patch key of each
        point (None: all one patch); a patch whose points would all be held out keeps them."""
        held = self.held_strips(self.strip_ids(gps_time, xy_world)) if len(gps_time) else np.zeros(0, bool)
        if not held.any():
            return held
        if patch is None:
            return held if not held.all() else np.zeros(len(held), bool)
        _, group = np.unique(np.asarray(patch, np.int64), return_inverse=True)
        kept = np.bincount(group.reshape(-1), weights=~held, minlength=group.max() + 1)
        return held & (kept[group.reshape(-1)] > 0)


__all__ = ["Holdout"]
