"""A LoD2-like block model of the synthetic buildings (``ms3d synth --coarse-mesh``), with labels.

A city model (CityGML/CityJSON LoD2 export, CAD) is each building's envelope in a few big planar faces:
walls, roof planes, eave soffits and fascias, without window and door recesses, balconies, ledges or
passages. :func:`make_coarse_mesh` triangulates the same envelope charts the truth and the MVS
simulator are built on (:func:`synth.buildings.charts_of`; a fan per chart, so faces are metres long)
and keeps the truth terrain (ground and road quads: a DTM), so only the buildings are generalised.

Labels: the truth surface (what the MLS sees) is sampled every ~``sample_step_m`` and a sample is a
defect sample where it lies farther than ``depart_m`` from the block model: glass and reveals of
windows and doors recessed more than ``depart_m`` ("recess"), balconies and ledges ("balcony"), the
walls and ceiling of a ground-floor through-passage (:mod:`synth.passages`, "passage"; its floor is
terrain, which the block model drops under its solid). One defect per (building, type), in the ``defects.json`` format :mod:`storage.workdir.labels` reads (``samples``
in the mesh frame; ``faces`` is empty: labels go by samples). Visibility from the road is not
modelled: a sample the MLS cannot see still labels its patch.

Frames and units: mesh frame, metres, float64.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from .buildings import charts_of
from .passages import in_passage
from .scene import CLASS_COLOR, FaceClass, Mesh, Scene, soup_to_mesh

# truth classes whose departure from the block model is a labelled defect, and its type
_DEFECT_TYPE = {FaceClass.GLASS: "recess", FaceClass.FRAME: "recess", FaceClass.WALL: "recess",
                FaceClass.BALCONY: "balcony"}


@dataclass(frozen=True)
class CoarseParams:
    """depart_m: a truth sample farther than this from the block model is a defect (LoD2 tolerance);
    sample_step_m: spacing of the truth samples (one per ``step**2`` of surface, at least one per face)."""

    depart_m: float = 0.2
    sample_step_m: float = 0.15


def _triangulate(polygon: np.ndarray) -> np.ndarray:
    """Fan of a planar envelope chart (convex or star-shaped from its reflex vertex): (m, 3, 3)."""
    from .envelope import triangulate_polygon

    return triangulate_polygon(polygon)


def _terrain(truth: Mesh, infos: list[dict]) -> Mesh:
    """The truth faces of no building (ground, roads) but a passage's floor (the block is solid there),
    vertices re-indexed; ``infos``: ``scene.meta['buildings']``."""
    keep = (truth.face_building < 0) & (in_passage(truth.triangles().mean(axis=1), infos) < 0)
    used, faces = np.unique(truth.faces[keep], return_inverse=True)
    return Mesh(truth.vertices[used], faces.reshape(-1, 3).astype(np.int64), truth.face_class[keep],
                truth.face_building[keep], truth.face_color[keep])


def block_model(scene: Scene) -> Mesh:
    """Terrain + each building's envelope charts as big triangles (classes WALL/ROOF/EAVE of the charts);
    solid through a passage (no floor, no walls, no ceiling)."""
    charts = charts_of(scene)
    parts = [_terrain(scene.truth, scene.meta.get("buildings", []))]
    for b in scene.buildings:
        soup = [(_triangulate(c.polygon), c.face_class, CLASS_COLOR[FaceClass(c.face_class)]) for c in charts[b.id]]
        parts.append(soup_to_mesh([s for s in soup if len(s[0])], b.id))
    return Mesh.concat(parts)


def _surface_samples(mesh: Mesh, face_mask: np.ndarray, step: float) -> tuple[np.ndarray, np.ndarray]:
    """Deterministic samples of the masked faces: a barycentric lattice of ~area / step**2 points per
    face (at least its centroid). Returns (xyz (n, 3) float64, face index (n,) int64)."""
    idx = np.flatnonzero(face_mask)
    tri = mesh.vertices[mesh.faces[idx]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    k = np.maximum(1, np.ceil(np.sqrt(2 * area) / step)).astype(np.int64)  # lattice divisions per face
    xyz, fid = [], []
    for kk in np.unique(k):  # few distinct values: one vectorised pass each
        sel = np.flatnonzero(k == kk)
        i, j = np.meshgrid(np.arange(kk), np.arange(kk), indexing="ij")
        ok = i + j < kk
        a, b = (i[ok] + 1 / 3) / kk, (j[ok] + 1 / 3) / kk  # cell centroids of the lower triangles
        t = tri[sel]
        p = t[:, None, 0] + a[None, :, None] * (t[:, None, 1] - t[:, None, 0]) + b[None, :, None] * (t[:, None, 2] - t[:, None, 0])
        xyz.append(p.reshape(-1, 3))
        fid.append(np.repeat(idx[sel], len(a)))
    if not xyz:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    return np.concatenate(xyz), np.concatenate(fid)


def _distance(model: Mesh, points: np.ndarray) -> np.ndarray:
    """Unsigned distance (n,) float64 metres from points to the model's surface (open3d, float32 around
    a local origin: ~1e-6 m here)."""
    origin = np.round(model.vertices.mean(axis=0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(model.vertices - origin, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(model.faces, np.uint32)))
    q = o3d.core.Tensor(np.ascontiguousarray(points - origin, np.float32))
    return scene.compute_distance(q).numpy().astype(np.float64)


def departure_defects(scene: Scene, model: Mesh, params: CoarseParams = CoarseParams()) -> list[dict]:
    """Defects where the truth buildings depart from ``model`` by more than ``params.depart_m``:
    [{"id", "type", "building", "samples", "bbox", "faces": [], "depart_m"}], one per (building, type)."""
    truth = scene.truth
    cls_ok = np.isin(truth.face_class, np.array([int(c) for c in _DEFECT_TYPE], np.uint8))
    # a passage's walls and ceiling: its own type, whatever their class (WALL, EAVE)
    tunnel = in_passage(truth.triangles().mean(axis=1), scene.meta.get("buildings", [])) == truth.face_building
    tunnel &= truth.face_building >= 0
    pts, fid = _surface_samples(truth, (truth.face_building >= 0) & (cls_ok | tunnel), params.sample_step_m)
    if not len(pts):
        return []
    far = _distance(model, pts) > params.depart_m
    pts, fid = pts[far], fid[far]
    names = np.array(["", *sorted(set(_DEFECT_TYPE.values())), "passage"])
    code = np.zeros(256, np.int64)
    for c, t in _DEFECT_TYPE.items():
        code[int(c)] = int(np.flatnonzero(names == t)[0])
    kind = np.where(tunnel[fid], "passage", names[code[truth.face_class[fid]]])
    out = []
    for bid in np.unique(truth.face_building[fid]):
        for t in ("recess", "balcony", "passage"):
            sel = (truth.face_building[fid] == bid) & (kind == t)
            if not sel.any():
                continue
            s = np.round(pts[sel], 4)
            out.append({"id": f"coarse_{int(bid)}_{t}", "type": t, "building": int(bid), "faces": [],
                        "depart_m": params.depart_m, "samples": s.tolist(),
                        "bbox": [*map(float, s.min(axis=0)), *map(float, s.max(axis=0))]})
    return out


def make_coarse_mesh(scene: Scene, params: CoarseParams = CoarseParams()) -> tuple[Mesh, list[dict]]:
    """The LoD2-like block model of ``scene`` and its labelled departures (see the module doc)."""
    model = block_model(scene)
    return model, departure_defects(scene, model, params)


__all__ = ["CoarseParams", "block_model", "departure_defects", "make_coarse_mesh"]
