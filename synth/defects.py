"""Labelled defects of a simulated photogrammetry mesh: holes, melted eaves, bumps, dents, warps.

Defects are placed on the building walls (the envelope wall charts), uniformly, as many as a
rate per 100 m^2 of wall gives, larger ones first, non-overlapping on one building. Deformations move mesh vertices (before
the MVS noise is added); holes remove faces (after it). Each defect is recorded as a dict:

    id            int, unique in the mesh
    type          "hole" | "occluded_hole" | "eave_hole" | "protrusion" | "melted_eave" | "recess"
                  | "dent" | "warp"
    building      building id
    centre        [x, y, z] metres, on the wall plane (eave types: on the wall top line)
    normal        [x, y, z] outward wall normal; axis_u: [x, y, z] horizontal axis along the wall
    radius_m      radius of the disc (on the wall plane) the defect covers
    magnitude_m   largest displacement (deformations); the radius for holes
    faces         indices of the affected faces in the FINAL mesh ([] for holes)
    samples       [[x, y, z], ...]: holes: the truth surface the hole removed, every ~sample_step_m;
                  deformations: the displaced vertices (final positions, one per ~edge length)
    bbox          [xmin, ymin, zmin, xmax, ymax, zmax] of the samples
    front_m, back_m  holes only: a face is removed when its centroid lies within radius_m of the
                  centre in the wall plane and between back_m behind and front_m in front of it,
                  and it belongs to the building with a class in HOLE_CLASSES.

Frames and units: mesh frame, metres.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from .scene import FaceClass, Mesh, Scene

DEFECT_TYPES = ("hole", "occluded_hole", "eave_hole", "protrusion", "melted_eave", "recess", "dent", "warp")
HOLE_TYPES = ("hole", "occluded_hole", "eave_hole")
HOLE_CLASSES = (FaceClass.WALL, FaceClass.GLASS, FaceClass.FRAME, FaceClass.BALCONY, FaceClass.EAVE)
FACADE_CLASSES = HOLE_CLASSES
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class DefectSpec:
    """rate_per_100m2: expected count per 100 m^2 of wall; radius_m, magnitude_m: uniform ranges."""

    rate_per_100m2: float
    radius_m: tuple[float, float]
    magnitude_m: tuple[float, float] = (0.0, 0.0)


def _default_specs() -> dict[str, DefectSpec]:
    return {  # tuned so that ~30-50 % of facade patches are touched (see facade_patch_bad_fraction)
        "hole": DefectSpec(0.86, (0.5, 1.5)),
        "occluded_hole": DefectSpec(0.48, (0.8, 1.8)),  # behind a tree, car, fence or pedestrian
        "eave_hole": DefectSpec(0.4, (0.6, 1.5)),  # at the wall top, through the soffit
        "protrusion": DefectSpec(0.72, (0.6, 1.6), (0.2, 1.0)),
        "melted_eave": DefectSpec(0.55, (0.8, 2.0), (0.2, 1.0)),
        "recess": DefectSpec(0.63, (0.6, 1.6), (0.1, 0.5)),
        "dent": DefectSpec(0.63, (0.4, 1.2), (0.1, 0.5)),
        "warp": DefectSpec(0.24, (2.5, 5.0), (0.1, 0.35)),
    }


@dataclass(frozen=True)
class DefectParams:
    """Rates and sizes of injected defects (see ``DefectSpec``)."""

    specs: dict[str, DefectSpec] = field(default_factory=_default_specs)
    affected_min_m: float = 0.03  # a vertex counts as deformed from this displacement on
    hole_front_m: float = 1.7  # hole cylinder reach in front of the wall (takes balcony blobs too)
    hole_back_m: float = 0.5  # and behind it (window recesses)
    sample_step_m: float = 0.1
    gap_m: float = 0.3  # minimum gap between two defect discs on one building
    occluder_reach_m: float = 10.0  # an occluder this close in front of a wall can cause an occluded hole


def wall_records(charts) -> list[dict]:
    """Walls from envelope charts [(building, Chart)]: building, P0 (3,) bottom-left corner, t (3,)
    along the wall, n (3,) outward, L (m), H (m, height of the rectangular part), area (m^2),
    eave (bool: a soffit runs along its top)."""
    out = []
    for bid, c in charts:
        if c is None or c.kind != "wall":
            continue
        n = c.normal
        t = np.cross(_Z, n)
        u = c.polygon @ t
        P0 = c.polygon[np.argmin(u)].copy()
        P0[2] = 0.0
        L, H = float(np.ptp(u)), float(c.rect_height_m)
        out.append({"building": bid, "P0": P0, "t": t, "n": n, "L": L, "H": H, "area": L * H,
                    "eave": len(c.polygon) == 4})
    return out


def _occluder_spots(scene: Scene, walls, reach) -> list[tuple[int, float, float]]:
    """(wall index, u, v) of the wall point straight behind each occluder (nearest wall in front of it)."""
    spots = []
    for o in scene.meta.get("occluders", []):
        b = np.asarray(o["bbox"], float)
        c = 0.5 * (b[:3] + b[3:])
        best = None
        for k, w in enumerate(walls):
            rel = c - w["P0"]
            s, u = rel @ w["n"], rel @ w["t"]
            if 0 < s < reach and 0 <= u <= w["L"] and (best is None or s < best[0]):
                best = (s, k, u)
        if best is not None:
            z = c[2] if o["class"] != "TREE" else min(c[2], b[2] + 0.5 * (b[5] - b[2]))
            spots.append((best[1], best[2], float(z)))
    return spots


def plan_defects(rng, walls: list[dict], scene: Scene, p: DefectParams) -> list[dict]:
    """Choose type, wall, centre, radius and magnitude of every defect (no mesh needed)."""
    if not walls:
        return []
    area = np.array([w["area"] for w in walls])
    eave_w = area * np.array([w["eave"] for w in walls])
    spots = _occluder_spots(scene, walls, p.occluder_reach_m)
    rng.shuffle(spots)
    draws = []
    for typ in DEFECT_TYPES:
        spec = p.specs.get(typ)
        if spec is not None and spec.rate_per_100m2 > 0:
            lam = spec.rate_per_100m2 * area.sum() / 100.0
            n = int(lam) + int(rng.random() < lam - int(lam))  # the expected count, not Poisson: steadier labels
            draws += [(typ, float(r)) for r in rng.uniform(*spec.radius_m, n)]
    draws.sort(key=lambda d: -d[1])  # large defects first, while the walls are still free
    plan = []
    for typ, r in draws:
        spec = p.specs[typ]
        for _try in range(20):
            if typ == "occluded_hole":
                if not spots:
                    break
                k, u, v = spots.pop()
            else:
                wts = eave_w if typ in ("eave_hole", "melted_eave") else area
                if wts.sum() <= 0:
                    break
                k = int(rng.choice(len(walls), p=wts / wts.sum()))
                top = walls[k]["H"]
                if walls[k]["L"] < 2 * r or (typ not in ("eave_hole", "melted_eave") and top - r < r + 0.3):
                    continue
                u = rng.uniform(r, walls[k]["L"] - r)
                v = top - rng.uniform(0.0, 0.25) * r if typ in ("eave_hole", "melted_eave") else \
                    rng.uniform(r + 0.3, top - r)
            w = walls[k]
            u = float(np.clip(u, r, w["L"] - r))
            v = float(min(max(v, r + 0.3), w["H"]))
            if not (r <= u <= w["L"] - r) or v - r < 0.3 - 1e-9:
                continue
            c = w["P0"] + u * w["t"] + v * _Z
            if any(q["building"] == w["building"] and np.linalg.norm(q["centre"] - c) < q["radius_m"] + r + p.gap_m
                   for q in plan):
                continue
            m = r if typ in HOLE_TYPES else float(rng.uniform(*spec.magnitude_m))
            plan.append({"type": typ, "building": int(w["building"]), "centre": c, "normal": w["n"],
                         "axis_u": w["t"], "radius_m": r, "magnitude_m": m, "wall_top_z": w["H"]})
            break
    return plan


def _displacement(d: dict, v: np.ndarray) -> np.ndarray:
    """Displacement vectors (n, 3) of vertices v (n, 3) (already restricted to d's building)."""
    rel = v - d["centre"]
    du, dv, dn = rel @ d["axis_u"], rel[:, 2], rel @ d["normal"]
    r, m, n = d["radius_m"], d["magnitude_m"], d["normal"]
    if d["type"] == "melted_eave":
        rho = np.linalg.norm(rel, axis=1) / r
        direction = (n - 0.7 * _Z) / np.linalg.norm(n - 0.7 * _Z)
        return (m * np.clip(1 - rho ** 2, 0, None) ** 2)[:, None] * direction
    rho = np.hypot(du, dv) / r
    bump = np.clip(1 - rho ** 2, 0, None) ** 2 * ((dn > -0.6) & (dn < 1.8))
    s = {"protrusion": bump, "dent": -bump,
         "recess": -np.where(rho < 0.5, 1.0, 0.5 * (1 + np.cos(np.pi * np.clip((rho - 0.5) / 0.5, 0, 1))))
         * (rho < 1) * ((dn > -0.6) & (dn < 1.8)),
         "warp": np.sin(np.pi * du / r) * bump}[d["type"]]
    return (m * s)[:, None] * n


def _hole_samples(d, near, truth: Mesh, step, front, back, overhang) -> np.ndarray:
    """Truth surface points inside a hole: rays onto the wall region, plus up onto the soffit (eave holes)."""
    r, c, n, t = d["radius_m"], d["centre"], d["normal"], d["axis_u"]
    g = np.arange(-r, r + 1e-9, step)
    A, B = np.meshgrid(g, g)
    sel = A ** 2 + B ** 2 < r ** 2
    q = c + A[sel][:, None] * t + B[sel][:, None] * _Z
    tt, prim = near.cast(q + front * n, np.tile(-n, (len(q), 1)))
    f = near.face_index[np.maximum(prim, 0)]
    ok = (prim >= 0) & (tt < front + back) & (truth.face_building[f] == d["building"])
    pts = [q[ok] + (front - tt[ok])[:, None] * n]
    if d["type"] == "eave_hole" and overhang > 0:
        a = g[np.abs(g) < r]
        W = np.arange(step / 2, overhang, step)
        A2, W2 = np.meshgrid(a, W)
        q2 = c + A2.ravel()[:, None] * t + W2.ravel()[:, None] * n - [0, 0, 1.0]
        tt, prim = near.cast(q2, np.tile(_Z, (len(q2), 1)))
        f = near.face_index[np.maximum(prim, 0)]
        hit = q2 + np.where(np.isfinite(tt), tt, 0)[:, None] * _Z
        ok = ((prim >= 0) & (truth.face_building[f] == d["building"]) & (truth.face_class[f] == FaceClass.EAVE)
              & (np.hypot(A2.ravel(), hit[:, 2] - c[2]) < r))
        pts.append(hit[ok])
    return np.concatenate(pts)


def inject_defects(rng, mesh: Mesh, walls: list[dict], scene: Scene, p: DefectParams, add_noise, near
                   ) -> tuple[Mesh, list[dict]]:
    """Deform, add noise (``add_noise(vertices) -> vertices``), cut holes; return (mesh, defects).

    mesh: the noise-free MVS mesh (not modified); walls: ``wall_records``; near: a
    ``synth.mvs.TruthCaster`` over the whole truth (to sample the surface a hole removed).
    """
    plan = plan_defects(rng, walls, scene, p)
    v = mesh.vertices.copy()
    faces = mesh.faces
    vb = np.full(len(v), -1, np.int64)
    bf = mesh.face_building >= 0
    vb[faces[bf].ravel()] = np.repeat(mesh.face_building[bf], 3)  # buildings never share a vertex
    tree = cKDTree(v)
    inc_order = np.argsort(faces.ravel(), kind="stable")  # vertex -> incident faces
    inc_start = np.searchsorted(faces.ravel()[inc_order], np.arange(len(v) + 1))

    def faces_of(vid):
        lens = inc_start[vid + 1] - inc_start[vid]
        pos = np.repeat(inc_start[vid], lens) + (np.arange(lens.sum()) - np.repeat(np.cumsum(lens) - lens, lens))
        return np.unique(inc_order[pos] // 3)

    def ball(d, reach):
        idx = np.asarray(tree.query_ball_point(d["centre"], reach), np.int64)
        return idx[vb[idx] == d["building"]]

    affected = []
    for d in plan:
        if d["type"] in HOLE_TYPES:
            affected.append(None)
            continue
        idx = ball(d, np.hypot(d["radius_m"], 1.8))
        dv = _displacement(d, v[idx])
        v[idx] += dv
        affected.append(idx[np.linalg.norm(dv, axis=1) >= p.affected_min_m])
    v = add_noise(v)
    keep = np.ones(len(faces), bool)
    overhang = {b["id"]: b["overhang_m"] for b in scene.meta["buildings"]}
    holeable = np.isin(mesh.face_class, HOLE_CLASSES)
    for d in plan:
        if d["type"] not in HOLE_TYPES:
            continue
        d["front_m"] = overhang[d["building"]] + 0.3 if d["type"] == "eave_hole" else p.hole_front_m
        d["back_m"] = p.hole_back_m
        fi = faces_of(ball(d, np.hypot(d["radius_m"], d["front_m"]) + 0.5))
        fi = fi[holeable[fi] & (mesh.face_building[fi] == d["building"])]
        rel = v[faces[fi]].mean(axis=1) - d["centre"]
        dn = rel @ d["normal"]
        gone = (np.hypot(rel @ d["axis_u"], rel[:, 2]) < d["radius_m"]) & (dn > -d["back_m"]) & (dn < d["front_m"])
        keep[fi[gone]] = False
    new_face = np.cumsum(keep) - 1
    used, vremap = np.unique(faces[keep], return_inverse=True)
    out = Mesh(v[used], vremap.reshape(-1, 3).astype(np.int64), mesh.face_class[keep], mesh.face_building[keep],
               mesh.face_color[keep])
    defects = []
    for d, aff in zip(plan, affected):
        if d["type"] in HOLE_TYPES:
            samples = _hole_samples(d, near, scene.truth, p.sample_step_m, d["front_m"], d["back_m"],
                                    overhang[d["building"]])
            fidx = np.zeros(0, np.int64)
        else:
            samples = v[aff]
            old = faces_of(aff)
            fidx = new_face[old[keep[old]]]
        if not len(samples):
            continue
        samples = np.round(samples, 4)  # 0.1 mm, plenty for labels and small in JSON
        rec = {"id": len(defects), "type": d["type"], "building": d["building"],
               "centre": [float(x) for x in d["centre"]], "normal": [float(x) for x in d["normal"]],
               "axis_u": [float(x) for x in d["axis_u"]], "radius_m": float(d["radius_m"]),
               "magnitude_m": float(d["magnitude_m"]), "faces": fidx.astype(int).tolist(),
               "samples": samples.tolist(),
               "bbox": [*map(float, samples.min(axis=0)), *map(float, samples.max(axis=0))]}
        if d["type"] in HOLE_TYPES:
            rec["front_m"], rec["back_m"] = float(d["front_m"]), float(d["back_m"])
        defects.append(rec)
    return out, defects


def facade_patch_bad_fraction(mesh: Mesh, defects: list[dict], patch_size=(2.3, 1.0, 0.7)) -> float:
    """Fraction of facade patches touched by a defect.

    A patch is a cell of the global grid floor(xyz / patch_size); it is a facade patch when it holds
    the centroid of a facade face (class in FACADE_CLASSES, building >= 0) or a hole sample; it is
    touched when it holds a defect sample or the centroid of a defect face.
    """
    size = np.asarray(patch_size, float)

    def cells(x):  # unique int64 keys of the patches holding points x (n, 3)
        ijk = np.floor(np.asarray(x, float).reshape(-1, 3) / size).astype(np.int64) + (1 << 20)
        return np.unique((ijk[:, 0] << 42) | (ijk[:, 1] << 21) | ijk[:, 2])

    cen = mesh.triangles().mean(axis=1)
    fac = np.isin(mesh.face_class, FACADE_CLASSES) & (mesh.face_building >= 0)
    facade = [cells(cen[fac])]
    touched = [np.zeros(0, np.int64)]
    for d in defects:
        touched.append(cells(d["samples"]))
        if d["faces"]:
            touched.append(cells(cen[np.asarray(d["faces"], np.int64)]))
        if d["type"] in HOLE_TYPES:
            facade.append(touched[-1])
    facade = np.unique(np.concatenate(facade))
    return len(np.intersect1d(np.concatenate(touched), facade)) / max(len(facade), 1)
