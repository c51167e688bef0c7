"""Surface the mesh has no faces for at all: rebuilt from the MLS points alone.

A region's charts rebuild the faces it replaces; the fused points they take lie within
``max_map_distance_m`` of those faces. What the MLS sees far from every face of the region and *behind*
the surface (:func:`behind_surface`: inside the solid, e.g. the walls and ceiling of a passage through
a city model's block) has no chart to land in. Points in front of the surface (trees, cars, people,
unclassified) are never meshed this way: they are not the building. :func:`free_surface` meshes those points on their own: screened Poisson (open3d)
of the points with consistently oriented PCA normals, cut back to where the points are (vertices
farther than ``keep_m`` from every point go, with their faces), and long faces dropped. The result
has new vertices only (local ids); it is not welded to the retained mesh (it has no border there).

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from tasks.geometry.triangles import face_areas


def far_points(pts: np.ndarray, xyz: np.ndarray, faces: np.ndarray, reach_m: float) -> np.ndarray:
    """(k,) bool: points (k, 3) farther than reach_m from the surface (xyz (n, 3), faces (m, 3))."""
    from tasks.repair.mesh import ClosestPoint

    if not len(pts):
        return np.zeros(0, bool)
    if not len(faces):
        return np.ones(len(pts), bool)
    _, _, d = ClosestPoint(xyz, faces).query(pts)
    return d > reach_m


def behind_surface(pts: np.ndarray, xyz: np.ndarray, faces: np.ndarray, depth_m: float) -> np.ndarray:
    """(k,) bool: points (k, 3) more than depth_m behind their closest face (xyz (n, 3), faces (m, 3)),
    i.e. inside the solid the faces' outward orientation bounds: a passage through a block, not a
    tree or a car in front of a facade. No faces: none.

    >>> xyz = np.array([[0, 0, 0], [4, 0, 0], [4, 0, 3], [0, 0, 3]], float)   # a wall facing -y
    >>> f = np.array([[0, 1, 2], [0, 2, 3]])
    >>> behind_surface(np.array([[1.0, 2.0, 1.0], [1.0, -2.0, 1.0]]), xyz, f, 0.25).tolist()
    [True, False]
    """
    from tasks.repair.mesh import ClosestPoint

    if not (len(pts) and len(faces)):
        return np.zeros(len(pts), bool)
    xyz = np.asarray(xyz, np.float64)
    fid, bary, _ = ClosestPoint(xyz, faces).query(pts)
    tri = xyz[faces[np.maximum(fid, 0)]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-18)[:, None]
    foot = np.einsum("kc,kcd->kd", bary, tri)
    return (fid >= 0) & (np.einsum("ij,ij->i", pts - foot, n) < -depth_m)


def free_surface(pts: np.ndarray, *, min_points: int = 50, normal_k: int = 12, depth: int = 8,
                 keep_factor: float = 2.0, max_edge_factor: float = 4.0) -> tuple[np.ndarray, np.ndarray, dict]:
    """Mesh points (k, 3) float64 that no face stands near.

    The points' spacing s is their median nearest-neighbour distance; Poisson vertices farther than
    keep_factor * s from every point are cut, and faces with an edge longer than max_edge_factor * s.
    Returns ((v, 3) float64 vertices, (f, 3) int64 faces, stats); empty below min_points.

    >>> g = np.stack(np.meshgrid(np.arange(0, 4, 0.1), np.arange(0, 3, 0.1)), -1).reshape(-1, 2)
    >>> v, f, st = free_surface(np.c_[g[:, 0], np.zeros(len(g)), g[:, 1]])
    >>> bool(len(f) > 100 and np.abs(v[:, 1]).max() < 0.05)
    True
    """
    import open3d as o3d

    from tasks.repair.mesh import poisson_depth_for

    stats = {"points": len(pts)}
    empty = np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    if len(pts) < min_points:
        return *empty, stats
    c = pts.mean(axis=0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts - c))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(normal_k))
    try:
        pcd.orient_normals_consistent_tangent_plane(normal_k)
    except RuntimeError:  # Qhull fails on co-planar / co-spherical input: one side of a plane is consistent
        n = np.asarray(pcd.normals)
        ref = np.linalg.svd(n, full_matrices=False)[2][0]
        pcd.normals = o3d.utility.Vector3dVector(np.where((n @ ref < 0)[:, None], -n, n))
    tree = cKDTree(pts)
    spacing = float(np.median(tree.query(pts, k=2)[0][:, 1]))
    d = poisson_depth_for(float(np.ptp(pts, axis=0).max()), max(spacing, 1e-3), hi=depth)
    with o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error):
        mesh, _ = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=d, linear_fit=False, n_threads=1)
    v = np.asarray(mesh.vertices) + c
    f = np.asarray(mesh.triangles, np.int64)
    near = tree.query(v, distance_upper_bound=keep_factor * spacing)[0] < np.inf
    f = f[near[f].all(axis=1)]
    if len(f):
        e = v[f]
        longest = np.linalg.norm(e - np.roll(e, 1, axis=1), axis=2).max(axis=1)
        f = f[longest <= max_edge_factor * spacing]
    used, inv = np.unique(f, return_inverse=True)
    v, f = v[used], inv.reshape(-1, 3).astype(np.int64)
    stats |= {"spacing_m": spacing, "depth": d, "faces": len(f),
              "area_m2": float(face_areas(v, f, np.float64).sum()) if len(f) else 0.0}
    return v, f, stats


__all__ = ["behind_surface", "far_points", "free_surface"]
