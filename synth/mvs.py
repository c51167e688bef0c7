"""A UAV photogrammetry (ContextCapture-like) mesh simulated from the truth, with labelled defects.

How it is built, per building and for the terrain:

1. every envelope chart (``synth.envelope``: walls, soffits, fascias, roof planes) and every
   terrain cell (``synth.terrain.terrain_cells``) is covered with staggered rows of near-
   equilateral triangles of edge ``edge_*_m``, slightly jittered; chart edges are sampled the same
   way from both sides, so the charts weld into one connected, manifold surface whose only border
   is the extent's; a few random edge flips bring valence-6 vertices down to real-mesh levels;
2. wall vertices are moved along the wall normal onto the truth details seen from 1.8 m in front
   (glass at the back of window recesses, balcony fronts, ledges): balconies become solid blobs,
   recesses dips (only ``recess_gain`` of their depth: MVS bridges them); terrain vertices drop
   onto the ground/road surface;
3. that displacement is diffused over the wall (edges round off, balconies melt), corners are
   rounded by a little Taubin smoothing;
4. wall faces take class, building and colour from the truth faces their corners looked at (the
   nearest truth face where those differ), roof/soffit/fascia faces from their chart, terrain
   faces from the road grid;
5. defects are injected (``synth.defects``), then low-frequency (a few cm) and high-frequency
   (mm) noise along the vertex normals, then the holes are cut.

A building's through-passage (``synth.passages``) is opened in its facade charts and lined with its
own wall and ceiling charts (:func:`synth.passages.passage_charts`), welded like the rest; defects are
placed on the unsplit envelope. Occluders are not in this mesh. Frames and units: mesh frame, metres, float64.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from tasks.geometry.triangles import vertex_normals

from .buildings import charts_of
from .defects import DefectParams, inject_defects, wall_records
from .envelope import Chart, insert_points
from .lattice import NeighbourMean, random_edge_flips, strip_chart
from .passages import passage_charts
from .scene import CLASS_COLOR, FaceClass, Mesh, Scene

DETAIL_CLASSES = (FaceClass.WALL, FaceClass.GLASS, FaceClass.FRAME, FaceClass.BALCONY)


@dataclass(frozen=True)
class MvsParams:
    """Resolution, blur and noise of the simulated photogrammetry mesh."""

    edge_facade_m: float = 0.12  # walls, soffits, fascias, and every building chart edge
    edge_roof_m: float = 0.16  # roof plane interiors
    edge_ground_m: float = 0.40  # terrain interior (footprint edges use edge_facade_m)
    lattice_jitter: float = 0.2  # tangential jitter of lattice points, fraction of the edge
    flip_fraction: float = 0.006  # share of interior edges flipped (real meshes: ~91 % valence-6 vertices)
    ray_reach_m: float = 1.8  # wall details are looked for this far in front of the wall
    recess_gain: float = 0.6  # MVS bridges recesses: window/door depth kept (the rest fills in)
    blur_iterations: int = 6  # diffusion of the wall displacement (edges round off, balconies melt)
    blur_lambda: float = 0.5
    round_iterations: int = 1  # Taubin passes over the whole mesh (rounds corners)
    noise_lf_m: float = 0.015  # RMS of the smooth (long-wavelength) normal offset
    noise_lf_wavelength_m: tuple[float, float] = (2.0, 10.0)
    noise_hf_m: float = 0.008  # RMS of the per-vertex normal offset
    include_terrain: bool = True
    defects: DefectParams | None = field(default_factory=DefectParams)  # None: no defects


# -- helpers over the assembled mesh ---------------------------------------------------------------

class TruthCaster:
    """open3d ray casting / closest point over a subset of a Mesh's faces, in float32 around a local origin."""

    def __init__(self, mesh: Mesh, face_mask: np.ndarray | None = None):
        self.face_index = np.flatnonzero(np.ones(mesh.n_faces, bool) if face_mask is None else face_mask)
        f = mesh.faces[self.face_index]
        self.origin = np.round(mesh.vertices.mean(axis=0)) if len(mesh.vertices) else np.zeros(3)
        self.normals = mesh.face_normals()[self.face_index]
        self.scene = o3d.t.geometry.RaycastingScene()
        if len(f):
            self.scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(mesh.vertices - self.origin, np.float32)),
                                     o3d.core.Tensor(np.ascontiguousarray(f, np.uint32)))

    def cast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n, 3) origins and unit dirs -> (t (n,) float64, inf on a miss; local face index (n,), -1 on a miss)."""
        rays = np.empty((len(origins), 6), np.float32)
        rays[:, :3], rays[:, 3:] = origins - self.origin, dirs
        out = self.scene.cast_rays(o3d.core.Tensor(rays))
        t = out["t_hit"].numpy().astype(np.float64)
        prim = out["primitive_ids"].numpy().astype(np.int64)
        miss = ~np.isfinite(t)
        prim[miss] = -1
        return t, prim

    def closest(self, points: np.ndarray) -> np.ndarray:
        """(n, 3) -> local face index (n,) of the nearest face."""
        q = o3d.core.Tensor(np.ascontiguousarray(points - self.origin, np.float32))
        return self.scene.compute_closest_points(q)["primitive_ids"].numpy().astype(np.int64)


def _smooth_noise(rng, p, sigma, wavelengths, k=8) -> np.ndarray:
    """A smooth random field (n,) with RMS ``sigma``: a sum of k plane waves in 3D."""
    d = rng.normal(size=(k, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = rng.uniform(*wavelengths, k)
    phase = rng.uniform(0, 2 * np.pi, k)
    return sigma * np.sqrt(2.0 / k) * np.sin(2 * np.pi * (p @ d.T) / lam + phase).sum(axis=1)


# -- the simulator ---------------------------------------------------------------------------------

def _split_for_strips(c: Chart, xs, ys) -> list[np.ndarray]:
    """Chart polygon(s) ready for ``strip_chart``: a gable-end pentagon is cut into its rectangle and
    apex triangle; wall bottoms get the terrain grid lines as vertices (the terrain cells meet them)."""
    poly = c.polygon
    if c.kind != "wall":
        return [poly]
    pts = [np.array([x, y, 0.0]) for x in xs for y in ys]  # grid nodes; only those on the wall bottom matter
    bottom = poly[np.abs(poly[:, 2]) < 1e-9]
    if len(bottom):  # (pieces of a wall above a passage do not reach the ground)
        lo, hi = bottom[:, :2].min(axis=0) - 1e-9, bottom[:, :2].max(axis=0) + 1e-9
        pts = np.array([q for q in pts if np.all(q[:2] >= lo) and np.all(q[:2] <= hi)])
        if len(pts):
            poly = insert_points(poly, pts)
    if len(c.polygon) == 5 and c.polygon[:, 2].max() > c.rect_height_m + 1e-9:
        apex = int(np.argmax(poly[:, 2]))
        k = len(poly)
        tri = poly[[(apex - 1) % k, apex, (apex + 1) % k]]
        rest = np.delete(poly, apex, axis=0)
        return [rest, tri]
    return [poly]


def _lattices(rng, scene: Scene, p: MvsParams):
    """Chart lattices welded into one mesh.

    Returns vertices (n, 3), faces (m, 3), charts [(building, Chart)] (the unsplit building charts),
    wall_n (n, 3) per-vertex wall normal (zeros off walls), face_kind (m,) 0 terrain / 1 wall /
    2 other building chart, face_part (m,) lattice part index, part_class and part_building per
    part, roads [(axis, centre, half_width)].
    """
    from .layout import road_lines
    from .terrain import terrain_cells

    eh = p.edge_facade_m * np.sqrt(3) / 2  # chart edges sampled at the row pitch of an equilateral lattice
    roads = [tuple(r) for r in scene.meta.get("roads", road_lines(scene.extent))]
    xs, ys, _, inside = terrain_cells(scene.extent, roads, scene.meta["buildings"])
    parts, charts, kinds, pclass, pbuild = [], [], [], [], []
    info = {d["id"]: d for d in scene.meta["buildings"]}
    for bid, chs in charts_of(scene).items():
        footprint = next(b.footprint for b in scene.buildings if b.id == bid)
        for c in passage_charts(chs, footprint, info[bid].get("passage")):
            inner = p.edge_roof_m if c.kind == "roof" else p.edge_facade_m
            for poly in _split_for_strips(c, xs, ys):
                parts.append(strip_chart(poly, [eh] * len(poly), inner, rng, p.lattice_jitter))
                kinds.append(c.normal if c.kind == "wall" else None)
                pclass.append(int(c.face_class))
                pbuild.append(bid)
        charts += [(bid, c) for c in chs]  # the unsplit envelope (defects are placed on it)
    n_building_parts = len(parts)
    if p.include_terrain:
        ge = p.edge_ground_m * np.sqrt(3) / 2
        pad = np.pad(inside, 1)
        for i, j in zip(*np.nonzero(~inside)):
            quad = np.array([[xs[i], ys[j], 0], [xs[i + 1], ys[j], 0], [xs[i + 1], ys[j + 1], 0],
                             [xs[i], ys[j + 1], 0]], float)
            nb = [pad[i + 1, j], pad[i + 2, j + 1], pad[i + 1, j + 2], pad[i, j + 1]]  # S, E, N, W neighbours
            parts.append(strip_chart(quad, [eh if b else ge for b in nb], p.edge_ground_m, rng, p.lattice_jitter))
            kinds.append(None)
    # weld the boundary samples shared between charts; interior vertices are unique already
    offs = np.cumsum([0] + [len(v) for v, _, _ in parts])
    allv = np.concatenate([v for v, _, _ in parts])
    bidx = np.flatnonzero(np.concatenate([b for _, _, b in parts]))
    _, first, inv = np.unique(np.round(allv[bidx], 5), axis=0, return_index=True, return_inverse=True)
    gid = np.arange(len(allv))
    gid[bidx] = bidx[first][inv.ravel()]
    used, remap = np.unique(gid, return_inverse=True)
    vertices = allv[used]
    faces = np.concatenate([remap[t + o] for (_, t, _), o in zip(parts, offs[:-1])])
    wall_n = np.zeros_like(vertices)
    for k, nrm in enumerate(kinds):
        if nrm is not None:
            wall_n[remap[offs[k]:offs[k + 1]]] = nrm
    face_part = np.concatenate([np.full(len(t), k, np.int64) for k, (_, t, _) in enumerate(parts)])
    part_kind = np.array([0 if k >= n_building_parts else (1 if nrm is not None else 2) for k, nrm in enumerate(kinds)])
    part_class = np.array(pclass + [FaceClass.GROUND] * (len(parts) - n_building_parts), np.uint8)
    part_building = np.array(pbuild + [-1] * (len(parts) - n_building_parts), np.int32)
    return vertices, faces, charts, wall_n, part_kind[face_part], face_part, part_class, part_building, roads


def _wall_details(v, wall_n, truth: Mesh, reach: float) -> tuple[np.ndarray, np.ndarray]:
    """Signed offset (n,) along wall_n from each wall vertex to the truth detail in front of / behind
    it (0 where none or off walls), and the truth face it looked at (n,) (-1 where none)."""
    is_wall = np.any(wall_n != 0, axis=1)
    disp, vsrc = np.zeros(len(v)), np.full(len(v), -1, np.int64)
    if is_wall.any():
        det = TruthCaster(truth, np.isin(truth.face_class, DETAIL_CLASSES) & (truth.face_building >= 0))
        t, prim = det.cast(v[is_wall] + wall_n[is_wall] * reach, -wall_n[is_wall])
        d = reach - t
        # facing the wall's way (glass, balcony fronts), not a reveal or a neighbouring wing's side
        ok = (prim >= 0) & (np.sum(det.normals[np.maximum(prim, 0)] * wall_n[is_wall], axis=1) > 0.5)
        ok &= (d > -0.6) & (d < reach - 0.02)
        disp[is_wall] = np.where(ok, d, 0.0)
        vsrc[is_wall] = np.where(ok, det.face_index[np.maximum(prim, 0)], -1)
    return disp, vsrc


def _transfer(v, faces, face_kind, face_part, part_class, part_building, vsrc, truth: Mesh, on_road):
    """Per-face class, building and colour: wall faces from the truth faces their corners looked at
    (the nearest truth face where those disagree), other building faces from their chart, terrain
    from the road grid."""
    m = len(faces)
    face_class, face_building = np.zeros(m, np.uint8), np.full(m, -1, np.int32)
    face_color = np.zeros((m, 3), np.uint8)
    wf = np.flatnonzero(face_kind == 1)
    src = vsrc[faces[wf]]
    cls = np.where(src >= 0, truth.face_class[np.maximum(src, 0)], 255)
    mixed = (cls[:, 0] == 255) | (cls[:, 0] != cls[:, 1]) | (cls[:, 0] != cls[:, 2])
    src = src[:, 0]
    near = TruthCaster(truth, truth.face_building >= 0)
    src[mixed] = near.face_index[near.closest(v[faces[wf[mixed]]].mean(axis=1))]
    face_class[wf], face_building[wf], face_color[wf] = truth.face_class[src], truth.face_building[src], \
        truth.face_color[src]
    of = np.flatnonzero(face_kind == 2)
    face_class[of], face_building[of] = part_class[face_part[of]], part_building[face_part[of]]
    tkey = truth.face_building.astype(np.int64) * 16 + truth.face_class
    uk, ui = np.unique(tkey, return_index=True)  # the truth colour of each (building, class)
    fk = face_building[of].astype(np.int64) * 16 + face_class[of]
    pos = np.minimum(np.searchsorted(uk, fk), len(uk) - 1)
    default = np.array([CLASS_COLOR[FaceClass(c)] for c in range(8)], np.uint8)
    face_color[of] = np.where((uk[pos] == fk)[:, None], truth.face_color[ui[pos]], default[face_class[of]])
    tf = face_kind == 0
    rd = on_road(v[faces[tf]].mean(axis=1)[:, :2])
    face_class[tf] = np.where(rd, FaceClass.ROAD, FaceClass.GROUND)
    face_color[tf] = default[face_class[tf]]
    return face_class, face_building, face_color


def make_mvs_mesh(rng: np.random.Generator, scene: Scene, params: MvsParams = MvsParams()
                  ) -> tuple[Mesh, list[dict]]:
    """Simulate the UAV photogrammetry mesh of ``scene`` and inject labelled defects.

    scene: from ``synth.buildings.make_scene`` (uses truth, buildings, extent and meta). Returns
    (mesh, defects): building faces carry the class/building/colour of the truth face they
    reproduce, terrain faces GROUND/ROAD with building -1; defects as listed in ``synth.defects``
    (face indices refer to the returned mesh). Deterministic in ``rng``.
    """
    truth = scene.truth
    v, faces, charts, wall_n, face_kind, face_part, part_class, part_building, roads = _lattices(rng, scene, params)
    if params.flip_fraction > 0:
        faces = random_edge_flips(v, faces, face_part, params.flip_fraction, rng)
    is_wall = np.any(wall_n != 0, axis=1)
    disp, vsrc = _wall_details(v, wall_n, truth, params.ray_reach_m)

    def on_road(xy):
        return np.any([np.abs(xy[:, ax] - c) < hw for ax, c, hw in roads], axis=0) if roads else \
            np.zeros(len(xy), bool)

    tv = np.zeros(len(v), bool)
    tv[faces[face_kind == 0].ravel()] = True
    tv &= ~is_wall
    v[tv, 2] = np.where(on_road(v[tv, :2]), scene.meta.get("layout", {}).get("road_z_m", 0.02), 0.0)
    disp = np.where(disp < 0, params.recess_gain * disp, disp)
    Mw = NeighbourMean(faces[face_kind == 1], len(v))
    for _ in range(params.blur_iterations):
        disp = np.where(is_wall, disp + params.blur_lambda * (Mw(disp) - disp), 0.0)
    v = v + wall_n * disp[:, None]
    M = NeighbourMean(faces, len(v))
    for _ in range(params.round_iterations):
        v = v + 0.5 * (M(v) - v)
        v = v - 0.53 * (M(v) - v)
    face_class, face_building, face_color = _transfer(v, faces, face_kind, face_part, part_class, part_building,
                                                      vsrc, truth, on_road)

    def add_noise(x):
        off = _smooth_noise(rng, x, params.noise_lf_m, params.noise_lf_wavelength_m)
        off = off + rng.normal(0.0, params.noise_hf_m, len(x))
        return x + vertex_normals(x, faces, order="corner_sums", eps=1e-12, undefined=None) * off[:, None]

    mesh = Mesh(v, faces, face_class, face_building, face_color)
    if params.defects is None:
        mesh.vertices = add_noise(mesh.vertices)
        return mesh, []
    return inject_defects(rng, mesh, wall_records(charts), scene, params.defects, add_noise, TruthCaster(truth))
