"""Labelled defects injected into any triangle mesh: the defect cases of a real photogrammetric mesh.

:mod:`synth.defects` places defects on the synth's wall charts; a real mesh has no charts. Here a defect is
a disc on a wall-like part of the mesh (faces whose normal is within ``max_normal_z`` of horizontal),
framed by the area-weighted normal of the faces around its centre. The real mesh is the truth, so the
labels are exact: every sample is a point of the surface the defect changed.

Types (a superset of what an MVS mesh gets wrong, after the paper's Fig. 1 and the synth):

    hole        faces within the disc removed (a hole; samples: the truth surface it removed)
    bridge      a recess bridged: vertices behind the disc's front plane pulled onto it (windows, doors)
    melt        a melted balcony or eave: a smooth sag forward and down
    protrusion  a blob in front of the wall; dent: pushed behind it
    offset      a flat-topped shift of the disc along its normal (a misplaced piece of surface)
    noise       vertex noise along the normal (a badly matched, rough area)
    thin        thin structures in front of the wall (faces more than ``thin_front_m`` in front of the
                disc's median plane) removed: columns, railings, mouldings missing

Each record has the fields of :mod:`synth.defects` (``id``, ``type``, ``centre``, ``normal``, ``axis_u``,
``radius_m``, ``magnitude_m``, ``faces`` in the output mesh, ``samples``, ``bbox``) with ``building`` -1,
so ``storage.workdir.labels`` labels patches from it. A planned defect that changes nothing (a bridge on a
flat wall, thin on a wall with nothing in front) is dropped. Frame and units: the mesh's, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .defects import DefectSpec  # rate per 100 m^2 of wall-like area, radius and magnitude ranges

MESH_DEFECT_TYPES = ("hole", "bridge", "melt", "protrusion", "dent", "offset", "noise", "thin")
_Z = np.array([0.0, 0.0, 1.0])


def _default_specs() -> dict[str, DefectSpec]:
    return {
        "hole": DefectSpec(0.8, (0.5, 1.5)),
        "bridge": DefectSpec(0.6, (0.6, 1.6)),
        "melt": DefectSpec(0.5, (0.8, 2.0), (0.2, 0.8)),
        "protrusion": DefectSpec(0.6, (0.6, 1.6), (0.2, 0.8)),
        "dent": DefectSpec(0.6, (0.5, 1.2), (0.1, 0.4)),
        "offset": DefectSpec(0.3, (1.0, 2.5), (0.1, 0.3)),
        "noise": DefectSpec(0.4, (0.8, 2.0), (0.05, 0.15)),
        "thin": DefectSpec(0.3, (0.8, 1.6)),
    }


@dataclass(frozen=True)
class MeshDefectParams:
    """Rates, sizes and thresholds of :func:`inject_mesh_defects` (metres)."""

    specs: dict[str, DefectSpec] = field(default_factory=_default_specs)
    max_normal_z: float = 0.4  # a defect centre sits on a face this close to vertical (|n_z| below it)
    min_height_m: float = 0.5  # and this far above the lowest vertex (not on the ground)
    affected_min_m: float = 0.03  # a vertex counts as changed from this displacement on
    hole_front_m: float = 1.0  # a hole removes faces this far in front of the disc plane
    hole_back_m: float = 0.5  # and this far behind it
    thin_front_m: float = 0.25  # "thin" removes the faces this far in front of the disc's median plane
    sample_step_m: float = 0.1  # removed surface sampled about this densely
    gap_m: float = 0.3  # the smallest gap between two defect discs
    rate_scale: float = 1.0  # every rate times this


def face_frames(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(centroids (m, 3), unit normals (m, 3), areas (m,) m^2) of the faces ``f`` (m, 3) over ``v`` (n, 3)."""
    t = v[f]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    a = np.linalg.norm(n, axis=1)
    return t.mean(1), n / np.maximum(a, 1e-30)[:, None], 0.5 * a


def disc_frame(centre: np.ndarray, radius: float, cent: np.ndarray, normals: np.ndarray, areas: np.ndarray,
               tree: cKDTree) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(normal, axis_u, axis_v) unit (3,) of a disc at ``centre``: the dominant normal (the principal axis of
    the area-weighted normals) of the faces whose centroid lies within ``radius``; axis_u horizontal along
    the wall. None where the normals cancel (a corner)."""
    idx = tree.query_ball_point(centre, radius)
    if not idx:
        return None
    mean = (normals[idx] * areas[idx, None]).sum(0)
    if np.linalg.norm(mean) < 0.5 * areas[idx].sum():  # a corner or a thin part: no one plane
        return None
    # the dominant direction of the normals (the recesses' and mouldings' sides do not tilt it), facing
    # the mean normal's way
    _, vec = np.linalg.eigh((normals[idx] * areas[idx, None]).T @ normals[idx])
    n = vec[:, 2] * np.sign(vec[:, 2] @ mean)
    near = np.asarray(idx)[normals[idx] @ n > np.cos(np.radians(15.0))]  # then the faces that face that way
    if len(near):
        n = (normals[near] * areas[near, None]).sum(0)
        n /= np.linalg.norm(n)
    u = np.cross(_Z, n)
    if np.linalg.norm(u) < 1e-6:
        return None
    u /= np.linalg.norm(u)
    return n, u, np.cross(n, u)


def plan_mesh_defects(rng: np.random.Generator, v: np.ndarray, f: np.ndarray, p: MeshDefectParams) -> list[dict]:
    """Type, centre, frame, radius and magnitude of every defect (large ones first, discs apart by ``gap_m``)."""
    cent, nrm, area = face_frames(v, f)
    wall = (np.abs(nrm[:, 2]) < p.max_normal_z) & (cent[:, 2] > v[:, 2].min() + p.min_height_m) & (area > 0)
    if not wall.any():
        return []
    wall_area = float(area[wall].sum())
    tree = cKDTree(cent)
    draws = []
    for typ in MESH_DEFECT_TYPES:
        spec = p.specs.get(typ)
        if spec is None or spec.rate_per_100m2 <= 0:
            continue
        lam = spec.rate_per_100m2 * p.rate_scale * wall_area / 100.0
        n = int(lam) + int(rng.random() < lam - int(lam))
        draws += [(typ, float(r)) for r in rng.uniform(*spec.radius_m, n)]
    draws.sort(key=lambda d: -d[1])
    weights = area * wall / wall_area
    plan: list[dict] = []
    for typ, r in draws:
        for _try in range(30):
            c = cent[int(rng.choice(len(f), p=weights))]
            if any(np.linalg.norm(q["centre"] - c) < q["radius_m"] + r + p.gap_m for q in plan):
                continue
            frame = disc_frame(c, r, cent, nrm, area, tree)
            if frame is None or abs(frame[0][2]) > p.max_normal_z:
                continue
            spec = p.specs[typ]
            m = r if typ in ("hole", "thin", "bridge") else float(rng.uniform(*spec.magnitude_m))
            plan.append({"type": typ, "centre": c, "normal": frame[0], "axis_u": frame[1], "axis_v": frame[2],
                         "radius_m": r, "magnitude_m": m})
            break
    return plan


def _window(rho: np.ndarray, flat: float = 0.0) -> np.ndarray:
    """(k,) a smooth window in [0, 1] of the in-plane radius ``rho`` (in radii): 1 up to ``flat``, 0 from 1."""
    x = np.clip((rho - flat) / max(1.0 - flat, 1e-9), 0.0, 1.0)
    return 0.5 * (1.0 + np.cos(np.pi * x)) * (rho < 1.0)


def displacement(d: dict, rel: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(k, 3) displacements of vertices at ``rel`` (k, 3) = vertex - centre, for a deforming defect ``d``."""
    n, u, w = d["normal"], d["axis_u"], d["axis_v"]
    du, dv, dn = rel @ u, rel @ w, rel @ n
    rho = np.hypot(du, dv) / d["radius_m"]
    m, typ = d["magnitude_m"], d["type"]
    slab = (dn > -0.6) & (dn < 1.5)
    if typ == "melt":
        direction = (n - 0.7 * _Z) / np.linalg.norm(n - 0.7 * _Z)
        s = np.clip(1 - (np.linalg.norm(rel, axis=1) / d["radius_m"]) ** 2, 0, None) ** 2
        return (m * s)[:, None] * direction
    if typ in ("protrusion", "dent"):
        s = np.clip(1 - rho ** 2, 0, None) ** 2 * slab * (1.0 if typ == "protrusion" else -1.0)
    elif typ == "offset":
        s = _window(rho, 0.6) * slab
    elif typ == "noise":
        s = _window(rho, 0.5) * slab * rng.standard_normal(len(rel))
    elif typ == "bridge":
        inside = (rho < 1.0) & slab
        front = float(np.percentile(dn[inside], 90)) if inside.sum() >= 8 else 0.0
        return (_window(rho, 0.7) * slab * np.clip(front - dn, 0.0, None))[:, None] * n
    else:
        raise ValueError(f"not a deforming defect type: {typ!r}")
    return (m * s)[:, None] * n


def sample_faces(tris: np.ndarray, step: float, rng: np.random.Generator) -> np.ndarray:
    """(s, 3) points on the triangles ``tris`` (k, 3, 3): about one per ``step``^2 of area, at least one each."""
    if not len(tris):
        return np.zeros((0, 3))
    a = 0.5 * np.linalg.norm(np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]), axis=1)
    k = np.maximum(1, np.ceil(a / step ** 2)).astype(np.int64)
    owner = np.repeat(np.arange(len(tris)), k)
    r1, r2 = rng.random(len(owner)), rng.random(len(owner))
    flip = r1 + r2 > 1
    r1, r2 = np.where(flip, 1 - r1, r1), np.where(flip, 1 - r2, r2)
    t = tris[owner]
    return t[:, 0] + r1[:, None] * (t[:, 1] - t[:, 0]) + r2[:, None] * (t[:, 2] - t[:, 0])


def _removed_faces(d: dict, cent: np.ndarray, ctree: cKDTree, p: MeshDefectParams) -> np.ndarray:
    """(k,) indices of the faces a hole or a thin defect removes."""
    reach = d["radius_m"] + max(p.hole_front_m, 1.5)
    idx = np.asarray(ctree.query_ball_point(d["centre"], reach), np.int64)
    if not len(idx):
        return idx
    rel = cent[idx] - d["centre"]
    rho = np.hypot(rel @ d["axis_u"], rel @ d["axis_v"]) / d["radius_m"]
    dn = rel @ d["normal"]
    if d["type"] == "hole":
        return idx[(rho < 1.0) & (dn > -p.hole_back_m) & (dn < p.hole_front_m)]
    disc = (rho < 1.0) & (dn > -p.hole_back_m) & (dn < 1.5)
    if disc.sum() < 8:
        return idx[:0]
    median = float(np.median(dn[disc]))
    gone = idx[disc & (dn > median + p.thin_front_m)]
    return gone if len(gone) >= 5 else idx[:0]


def inject_mesh_defects(rng: np.random.Generator, vertices: np.ndarray, faces: np.ndarray,
                        p: MeshDefectParams | None = None) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Deform and cut a copy of a mesh; returns (vertices (n', 3) float64, faces (m', 3) int64, defects).

    vertices (n, 3) metres, faces (m, 3) indices; the input is not modified. Deformations move vertices
    first (every face on a vertex moves with it), then holes and thin defects remove faces; unused
    vertices are dropped. Samples are in the mesh's frame (see the module docstring for the records)."""
    p = p or MeshDefectParams()
    v0 = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    plan = plan_mesh_defects(rng, v0, faces, p)
    v = v0.copy()
    vtree = cKDTree(v0)
    cent0, _, _ = face_frames(v0, faces)
    ctree = cKDTree(cent0)
    changed: list[np.ndarray | None] = []
    for d in plan:
        if d["type"] in ("hole", "thin"):
            changed.append(None)
            continue
        idx = np.asarray(vtree.query_ball_point(d["centre"], np.hypot(d["radius_m"], 1.5)), np.int64)
        dv = displacement(d, v0[idx] - d["centre"], rng) if len(idx) else np.zeros((0, 3))
        v[idx] += dv
        changed.append(idx[np.linalg.norm(dv, axis=1) >= p.affected_min_m])
    keep = np.ones(len(faces), bool)
    removed: list[np.ndarray] = []
    for d in plan:
        gone = _removed_faces(d, cent0, ctree, p) if d["type"] in ("hole", "thin") else np.zeros(0, np.int64)
        gone = gone[keep[gone]]  # a face belongs to one defect
        keep[gone] = False
        removed.append(gone)
    used, remap = np.unique(faces[keep], return_inverse=True)
    new_face = np.cumsum(keep) - 1
    vert_faces = np.argsort(faces.ravel(), kind="stable")
    starts = np.searchsorted(faces.ravel()[vert_faces], np.arange(len(v) + 1))
    defects = []
    for d, aff, gone in zip(plan, changed, removed):
        if aff is None:
            samples, fidx = sample_faces(v[faces[gone]], p.sample_step_m, rng), np.zeros(0, np.int64)
        else:
            samples = v[aff]
            inc = np.unique(np.concatenate([vert_faces[starts[i]:starts[i + 1]] for i in aff]) // 3) \
                if len(aff) else np.zeros(0, np.int64)
            fidx = new_face[inc[keep[inc]]]
        if not len(samples):
            continue
        samples = np.round(samples, 4)
        defects.append({"id": len(defects), "type": d["type"], "building": -1,
                        "centre": [float(x) for x in d["centre"]], "normal": [float(x) for x in d["normal"]],
                        "axis_u": [float(x) for x in d["axis_u"]], "radius_m": float(d["radius_m"]),
                        "magnitude_m": float(d["magnitude_m"]), "faces": fidx.astype(int).tolist(),
                        "samples": samples.tolist(),
                        "bbox": [*map(float, samples.min(axis=0)), *map(float, samples.max(axis=0))]})
    return v[used], remap.reshape(-1, 3).astype(np.int64), defects


__all__ = ["MESH_DEFECT_TYPES", "MeshDefectParams", "disc_frame", "displacement", "face_frames",
           "inject_mesh_defects", "plan_mesh_defects", "sample_faces"]
