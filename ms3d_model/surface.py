"""Scan points against a tile's whole surface: how far each point lies from the mesh, and in which direction.

The pair cues (:mod:`ms3d_model.cues`) measure a pair's points against the pair's own faces. A point near a
patch's side whose nearest surface belongs to the next cell then reads as "off the mesh", and nothing tells
a point in front of the wall from a point beside the wall's edge. Measured against every face of the tile,
a scan point's offset from its nearest surface point (its foot) splits into

- the component along the nearest face's normal: the scan sees the surface in front of or behind the mesh
  (an offset storey, a dent, a bridged recess), and
- the **in-plane** component: the scan sees surface where the mesh has none, beside the mesh's edge (a hole,
  a missing part).

The second is the evidence of a hole that a real production's structure cannot fake: a node border, a
crack, a texture seam or a sliver leaves the scan within millimetres of some face, while a hole leaves
scan points decimetres beside every face. Open edges (:func:`ms3d_model.cues.open_edge_flags`) are not read.

>>> import numpy as np
>>> wall = np.array([[[0, 0, 0], [2, 0, 0], [2, 0, 2]], [[0, 0, 0], [2, 0, 2], [0, 0, 2]]], float)  # x-z plane
>>> s = TileSurface.from_triangles(wall)
>>> d, off = s.nearest(np.array([[1.0, 0.3, 1.0], [2.5, 0.0, 1.0]]))
>>> d.round(3).tolist(), np.abs(off).round(3).tolist()  # 0.3 m in front; 0.5 m beside the edge, in-plane
([0.3, 0.5], [0.3, 0.0])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .kernels import nearest_of_candidates

K_CANDIDATES = 8  # faces with the nearest centres tried per point (the pair cues' value)


@dataclass
class TileSurface:
    """A tile's faces ready for nearest-surface queries.

    tri: (m, 3, 3) float64 corners (metres); normals: (m, 3) unit (0 for a zero-area face); radius: (m,)
    each face's largest corner distance from its centre; tree: a k-d tree of the (m, 3) centres."""

    tri: np.ndarray
    normals: np.ndarray
    radius: np.ndarray
    tree: cKDTree

    @classmethod
    def from_triangles(cls, tris: np.ndarray) -> TileSurface:
        """From (m, 3, 3) triangles (any float dtype; m >= 1)."""
        t = np.ascontiguousarray(tris, np.float64).reshape(-1, 3, 3)
        if not len(t):
            raise ValueError("a tile surface needs at least one face")
        cross = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        area2 = np.linalg.norm(cross, axis=1)
        normals = np.divide(cross, area2[:, None], out=np.zeros_like(cross), where=area2[:, None] > 0)
        centres = t.mean(axis=1)
        radius = np.linalg.norm(t - centres[:, None], axis=2).max(axis=1)
        return cls(t, normals, radius, cKDTree(centres, balanced_tree=False, compact_nodes=False))

    def __len__(self) -> int:
        return len(self.tri)

    def nearest(self, p: np.ndarray, k: int = K_CANDIDATES) -> tuple[np.ndarray, np.ndarray]:
        """(distance (q,), offset along the nearest face's normal (q,)) of points p (q, 3), metres, to the
        nearest of the ``k`` faces with the nearest centres (the exact nearest face in all but contrived
        cases: a face is tried whenever its centre is among the k nearest)."""
        p = np.ascontiguousarray(p, np.float64).reshape(-1, 3)
        if not len(p):
            return np.zeros(0), np.zeros(0)
        kk = min(k, len(self.tri))
        dc, fi = self.tree.query(p, k=kk)
        dc, fi = dc.reshape(len(p), kk), fi.reshape(len(p), kk)
        d, _, off = nearest_of_candidates(p, self.tri, self.normals, self.radius, fi.astype(np.int64), dc)
        return d, off


def in_plane(d: np.ndarray, off: np.ndarray) -> np.ndarray:
    """(q,) float64 the in-plane part of each offset: sqrt(d^2 - off^2), metres (0 for a foot inside a face)."""
    return np.sqrt(np.maximum(np.asarray(d, np.float64) ** 2 - np.asarray(off, np.float64) ** 2, 0.0))


__all__ = ["K_CANDIDATES", "TileSurface", "in_plane"]
