"""Ray casting against the truth mesh plus occluders (open3d ``RaycastingScene``, Embree).

The MLS simulator and the camera renderer share this: one BVH over both meshes, and a map from
open3d's (geometry id, primitive id) back to (source, face index) so every hit carries the face it
struck. open3d works in float32, so geometry and rays are shifted to a local origin (the mesh
bounding-box centre) first; at 1 km from that origin float32 still resolves ~0.06 mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .scene import Mesh

SOURCE_TRUTH = 0
SOURCE_OCCLUDER = 1
SOURCE_MISS = -1


@dataclass
class Hits:
    """First hits of n rays.

    t: (n,) float64 metres along the (unit) ray, inf on a miss; source: (n,) int8 SOURCE_TRUTH,
    SOURCE_OCCLUDER or SOURCE_MISS; face: (n,) int64 face index in that source mesh, -1 on a miss.
    """

    t: np.ndarray
    source: np.ndarray
    face: np.ndarray


class SceneCaster:
    """A BVH over ``truth`` and (optionally) ``occluders``; per-face class, colour and normal.

    truth, occluders: :class:`synth.scene.Mesh` (occluder face_class holds OccluderClass values).
    """

    def __init__(self, truth: Mesh, occluders: Mesh | None = None):
        meshes = [truth] + ([occluders] if occluders is not None and occluders.n_faces else [])
        allv = np.concatenate([m.vertices for m in meshes if len(m.vertices)] or [np.zeros((1, 3))])
        self.origin_m = np.round(0.5 * (allv.min(axis=0) + allv.max(axis=0)))
        self._scene = o3d.t.geometry.RaycastingScene()
        # geometry id -> source; arrays indexed [source] for class/colour/normal lookups
        self._geom_source = {}
        self.face_class: list[np.ndarray] = []
        self.face_color: list[np.ndarray] = []
        self.face_normal: list[np.ndarray] = []
        for source, m in enumerate(meshes):
            self.face_class.append(np.asarray(m.face_class, np.uint8))
            self.face_color.append(np.asarray(m.face_color, np.uint8))
            self.face_normal.append(m.face_normals() if m.n_faces else np.zeros((0, 3)))
            if not m.n_faces:
                continue
            v = o3d.core.Tensor(np.ascontiguousarray(m.vertices - self.origin_m, dtype=np.float32))
            f = o3d.core.Tensor(np.ascontiguousarray(m.faces, dtype=np.uint32))
            self._geom_source[self._scene.add_triangles(v, f)] = source
        self._face_offset = np.cumsum([0] + [m.n_faces for m in meshes])[:-1].astype(np.int64)
        self._all = [np.concatenate(tab) for tab in (self.face_class, self.face_color, self.face_normal)]

    def cast(self, origins: np.ndarray, dirs: np.ndarray, nthreads: int = 0) -> Hits:
        """origins, dirs: (n, 3) float64, mesh frame, dirs unit length -> :class:`Hits`."""
        rays = np.empty((len(dirs), 6), np.float32)
        rays[:, :3] = origins - self.origin_m
        rays[:, 3:] = dirs
        return self.cast_local(rays, nthreads)

    def cast_local(self, rays: np.ndarray, nthreads: int = 0) -> Hits:
        """rays: (n, 6) float32 C-contiguous, origin relative to ``self.origin_m`` then unit
        direction -> :class:`Hits`."""
        out = self._scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=nthreads)
        t = out["t_hit"].numpy().astype(np.float64)
        gid = out["geometry_ids"].numpy()
        hit = gid != o3d.t.geometry.RaycastingScene.INVALID_ID
        source = np.full(len(t), SOURCE_MISS, np.int8)
        for g, s in self._geom_source.items():
            source[gid == g] = s
        t[~hit] = np.inf
        face = np.where(hit, out["primitive_ids"].numpy().astype(np.int64), -1)
        return Hits(t=t, source=source, face=face)

    def global_face(self, source: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Row of each hit (source >= 0) in the concatenated per-face tables below: (n,) int64."""
        return face + self._face_offset[source]

    @property
    def all_face_class(self) -> np.ndarray:
        """(m_truth + m_occluders,) uint8: FaceClass rows, then OccluderClass rows."""
        return self._all[0]

    @property
    def all_face_color(self) -> np.ndarray:
        """(m_truth + m_occluders, 3) uint8 RGB."""
        return self._all[1]

    @property
    def all_face_normal(self) -> np.ndarray:
        """(m_truth + m_occluders, 3) float64 unit normals (by vertex order)."""
        return self._all[2]
