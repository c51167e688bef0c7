"""Input faces put back where the rebuild left nothing in their place (a repair the evidence does not support
is not applied).

:func:`tasks.repair.rebuilt.drop_unsupported` removes rebuilt faces that rest on neither the scan nor the
input: chords of the chart triangulation across a scan gap; the chart meshing itself drops over-long faces.
The zone faces they replaced are gone with them, so where the input was right and the scan did not see it (a
roof behind an eave, seen from the street), the model loses surface that nothing contradicted. Measured on
the real street corner (defect seeds 1 and 6): 0.25 and 0.13 m^2 of roof uncovered that the input held.

:func:`restorable_faces` names the zone faces to keep after all: those no face of the remaining rebuild
covers, and that no unexplained scan point names as its closest face (those are the surface the scan shows
wrong: :func:`tasks.repair.agree.unexplained_points`). With ``repair.mesh.restore_scope`` "dropped" only the
faces a dropped chord covered are candidates (halved the roof misses above); with "uncovered" (the default)
every replaced face is, but only where it continues the retained input (:func:`attached`): the side of a bump
cut back, an island inside the rebuild, stays replaced (on Sceaux, without that condition, such faces cost
0.001-0.002 of F@5cm for no covered area). "any" drops the contradiction test as well. A face covers a sample
when the sample lies within ``coplanar_m`` of it, or within ``depth_m`` along the sample's face normal (the
closest point on it within ``min_cos`` of that direction): a rebuilt wall 20 cm in front of an offset input
wall covers it; the facade beside a roof edge does not cover the roof.

Frames and units: campus-local metres, float64.
"""

from __future__ import annotations

import numpy as np


def _face_samples(xyz: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Four samples per face (centroid, and a third of the way from it to each corner): ((4m, 3) points,
    (4m,) face index, (4m, 3) unit face normals; zero for a degenerate face)."""
    tri = xyz[faces]
    c = tri.mean(axis=1)
    pts = np.concatenate([c[:, None], (2 * c[:, None] + tri) / 3], axis=1).reshape(-1, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)
    return pts, np.repeat(np.arange(len(faces)), 4), np.repeat(n, 4, axis=0)


def covered(pts: np.ndarray, normals: np.ndarray, xyz: np.ndarray, faces: np.ndarray, *, depth_m: float,
            min_cos: float = 0.7, coplanar_m: float = 0.02) -> np.ndarray:
    """(k,) bool: samples pts (k, 3) with unit normals (k, 3) covered by the surface (xyz (n, 3), faces (m, 3)).

    >>> xyz = np.array([[0, 0, 0.3], [2, 0, 0.3], [0, 2, 0.3]])          # a face 0.3 m above z = 0
    >>> pts, up = np.array([[0.5, 0.5, 0.0], [3.0, 0.5, 0.3]]), np.tile([0.0, 0.0, 1.0], (2, 1))
    >>> covered(pts, up, xyz, np.array([[0, 1, 2]]), depth_m=1.0).tolist()   # below it: yes; beside it: no
    [True, False]
    """
    from tasks.repair.mesh import ClosestPoint

    if not len(faces) or not len(pts):
        return np.zeros(len(pts), bool)
    fid, bary, d = ClosestPoint(xyz, faces).query(pts)
    cp = np.einsum("kj,kjc->kc", bary, xyz[faces[np.maximum(fid, 0)]])
    v = cp - pts
    along = np.abs(np.einsum("ij,ij->i", v, normals)) >= min_cos * np.maximum(d, 1e-12)
    return (fid >= 0) & ((d <= coplanar_m) | ((d <= depth_m) & along))


def restorable_faces(xyz: np.ndarray, zone_faces: np.ndarray, dropped: tuple[np.ndarray, np.ndarray] | None,
                     kept: tuple[np.ndarray, np.ndarray], contradicted: np.ndarray, *, depth_m: float,
                     min_cos: float = 0.7) -> np.ndarray:
    """(mz,) bool: zone faces (mz, 3) into xyz (n, 3) to put back: most of their samples covered by the
    ``dropped`` rebuilt faces ((v, 3) xyz, (d, 3) faces; None: every zone face is a candidate) and not by the
    ``kept`` ones, and not ``contradicted`` ((mz,) bool: the closest face of an unexplained scan point).

    >>> xyz = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [6, 0, 0], [5, 1, 0]], float)
    >>> zone = np.array([[0, 1, 2], [3, 4, 5]])
    >>> chord = (xyz + [0, 0, 0.4], zone)                           # both were rebuilt 0.4 m up, then dropped
    >>> none = (np.zeros((0, 3)), np.zeros((0, 3), np.int64))
    >>> restorable_faces(xyz, zone, chord, none, np.array([False, True]), depth_m=1.0).tolist()
    [True, False]
    >>> restorable_faces(xyz, zone, None, chord, np.array([False, False]), depth_m=1.0).tolist()  # still rebuilt
    [False, False]
    """
    mz = len(zone_faces)
    out = np.zeros(mz, bool)
    if not mz or (dropped is not None and not len(dropped[1])):
        return out
    pts, pf, nrm = _face_samples(xyz, zone_faces)
    if dropped is None:
        cand = np.ones(mz, bool)
    else:
        under = covered(pts, nrm, *dropped, depth_m=depth_m, min_cos=min_cos)
        cand = np.bincount(pf, weights=under, minlength=mz) > 2  # at least 3 of the 4 samples
    cand &= ~np.asarray(contradicted, bool)
    if cand.any() and len(kept[1]):
        s = np.isin(pf, np.flatnonzero(cand))
        still = covered(pts[s], nrm[s], *kept, depth_m=depth_m, min_cos=min_cos)
        cand[np.bincount(pf[s], weights=still, minlength=mz) >= 2] = False  # half or more already covered
    return cand


def attached(zone_faces: np.ndarray, context_faces: np.ndarray, cand: np.ndarray, n_vertices: int) -> np.ndarray:
    """(mz,) bool: the ``cand`` zone faces ((mz, 3) into n_vertices vertices) whose connected piece (faces
    sharing a vertex, among the candidates) touches a vertex of a retained (context) face: the input surface
    they continue is still there. An island inside the rebuild (the side of a bump cut back) is not.

    >>> zone = np.array([[0, 1, 2], [1, 2, 3], [5, 6, 7]])       # two joined faces, one island
    >>> attached(zone, np.array([[3, 4, 8]]), np.ones(3, bool), 9).tolist()
    [True, True, False]
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    cand = np.asarray(cand, bool)
    idx = np.flatnonzero(cand)
    out = np.zeros(len(zone_faces), bool)
    if not len(idx) or not len(context_faces):
        return out
    k = len(idx)
    rows = np.repeat(np.arange(k), 3)  # face nodes 0..k-1, vertex nodes k..k+n-1
    cols = k + zone_faces[idx].ravel()
    g = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(k + n_vertices, k + n_vertices))
    _, lab = connected_components(g, directed=False)
    on_retained = np.zeros(n_vertices, bool)
    on_retained[np.asarray(context_faces).ravel()] = True
    good = np.unique(lab[k + np.flatnonzero(on_retained)])
    out[idx] = np.isin(lab[:k], good)
    return out


__all__ = ["attached", "covered", "restorable_faces"]
