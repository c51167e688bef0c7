"""Exact unsigned point-to-triangle distances: open3d's ``RaycastingScene`` (float32, in a frame centred on
the mesh) finds the closest face, and the distance is re-measured on that face in float64.

    >>> import numpy as np
    >>> v = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0]], float)
    >>> d = point_to_mesh_distance(np.array([[1.0, 1.0, 0.25], [5.0, 0.0, 0.0]]), v, np.array([[0, 1, 2]]))
    >>> np.round(d, 6).tolist()
    [0.25, 1.0]
"""

from __future__ import annotations

import numpy as np
import open3d as o3d

from ms3d_model.kernels import closest_points_numpy
from tasks.geometry.triangles import face_normals as unit_face_normals


class MeshDistance:
    """An open3d scene over faces of a mesh, in a float64 frame centred on them (float32 inside)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        mask = np.zeros(len(vertices), bool)
        mask[faces.ravel()] = True  # the vertices faces use, renumbered in order (np.unique, in O(n))
        self.faces = (np.cumsum(mask) - 1)[faces].reshape(-1, 3)
        v = vertices[mask]
        self.centre = 0.5 * (v.min(0) + v.max(0)) if len(v) else np.zeros(3)
        self.vertices = v - self.centre
        self.scene = None
        if len(self.faces):
            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(
                o3d.core.Tensor(self.vertices.astype(np.float32)),
                o3d.core.Tensor(self.faces.astype(np.uint32)),
            )

    def query(self, points: np.ndarray, exact: bool = True):
        """points: (k, 3) float64 input frame -> distances (k,) float64 m, face ids (k,) int64 (-1: none)."""
        if self.scene is None:
            return np.full(len(points), np.inf), np.full(len(points), -1, np.int64)
        p = points - self.centre
        out = self.scene.compute_closest_points(o3d.core.Tensor(p.astype(np.float32)))
        prim = out["primitive_ids"].numpy().astype(np.int64)
        ok = prim < len(self.faces)  # INVALID_ID (2**32 - 1) when nothing was found
        d = np.linalg.norm(p - out["points"].numpy().astype(np.float64), axis=1)
        d[~ok] = np.inf
        if exact and ok.any():
            tri = self.vertices[self.faces[prim[ok]]]
            q = closest_points_numpy(p[ok], tri[:, 0], tri[:, 1], tri[:, 2])
            d64 = np.linalg.norm(p[ok] - q, axis=1)
            d[ok] = np.where(np.isfinite(d64), d64, d[ok])  # degenerate faces keep the float32 value
        return d, np.where(ok, prim, -1)

    def covered_along(self, points: np.ndarray, normals: np.ndarray, half_m: float) -> np.ndarray:
        """(k,) bool: the mesh crosses the segment points +- half_m * normals ((k, 3) unit vectors)."""
        if self.scene is None or len(points) == 0:
            return np.zeros(len(points), bool)
        rays = np.concatenate([points - self.centre - half_m * normals, normals], 1).astype(np.float32)
        return self.scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy() <= 2 * half_m


def point_to_mesh_distance(points, vertices, faces, *, return_faces=False, exact=True, chunk_size=1_000_000):
    """Exact unsigned distance from each point to a triangle set.

    points: (k, 3) float64 metres; vertices: (n, 3) float64 metres, same frame; faces: (m, 3) int64.
    Returns (k,) float64 metres (inf when the mesh is empty), and with ``return_faces`` also the
    (k,) int64 index of the closest face (-1 when none). Large world coordinates are safe: open3d
    works in float32 around the mesh's centre and ``exact`` re-measures on the found face in float64.
    """
    points, vertices = np.asarray(points, np.float64), np.asarray(vertices, np.float64)
    md = MeshDistance(vertices, np.asarray(faces, np.int64))
    d, fid = np.empty(len(points)), np.empty(len(points), np.int64)
    for lo in range(0, len(points), chunk_size):
        d[lo : lo + chunk_size], fid[lo : lo + chunk_size] = md.query(points[lo : lo + chunk_size], exact)
    return (d, fid) if return_faces else d


__all__ = ["MeshDistance", "point_to_mesh_distance", "unit_face_normals"]
