"""Levels of detail for export: vertex-coloured meshes in ENU, quadric decimation, measured deviation.

A :class:`LodMesh` is what a quadtree node passes to its parent: float32 ENU positions (z-up), faces,
sRGB vertex colours (textures sampled at the vertices) and per-face provenance. Each node passes up
``decimate(content, content_faces / 4)``; a parent's content is its children's passed-up meshes welded
together. The deviation of each decimation is measured (sampled two-sided Hausdorff distance, open3d)
so a parent's ``geometricError`` is a measured bound of its distance to the full-resolution leaves:
``max over children (hausdorff(child content, child passed-up) + child geometricError)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import atomic_path
from storage.errors import InputError


@dataclass(frozen=True, eq=False)
class LodMesh:
    """positions: (n, 3) float32 metres ENU (z up). faces: (m, 3) int32. colors: (n, 3) uint8 sRGB.
    grade / source: (m,) int8, region: (m,) int32 (see storage.contracts.tile_mesh).
    A textured mesh (:mod:`tasks.export.bake`) also has uv: (n, 2) float32 (glTF convention) into
    atlas: (H, W, 3) uint8; the colours stay, as the fallback and for decimation."""

    positions: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    grade: np.ndarray
    source: np.ndarray
    region: np.ndarray
    uv: np.ndarray | None = None
    atlas: np.ndarray | None = None

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) (3,) float64 of the positions used by faces."""
        if not self.n_faces:
            used = self.positions
        else:
            mask = np.zeros(len(self.positions), bool)
            mask[self.faces.reshape(-1)] = True  # linear, no sort
            used = self.positions if mask.all() else self.positions[mask]
        return used.min(axis=0).astype(np.float64), used.max(axis=0).astype(np.float64)


_FIELDS = ("positions", "faces", "colors", "grade", "source", "region")
_TEXTURE_FIELDS = ("uv", "atlas")


def save_lod(path: str | Path, lod: LodMesh) -> None:
    arrays = {k: getattr(lod, k) for k in _FIELDS + _TEXTURE_FIELDS if getattr(lod, k) is not None}
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)


def load_lod(path: str | Path) -> LodMesh:
    recorded.ensure_local(path)  # a work dir on a bucket: downloaded when read
    with np.load(path, allow_pickle=False) as z:
        return LodMesh(**{k: z[k] for k in _FIELDS + _TEXTURE_FIELDS if k in z.files})


def concat_lods(parts: list[LodMesh]) -> LodMesh:
    """One LodMesh of ``parts`` (face indices shifted), not yet welded."""
    base = np.cumsum([0] + [len(p.positions) for p in parts[:-1]])
    return LodMesh(
        positions=np.concatenate([p.positions for p in parts]),
        faces=np.concatenate([p.faces + np.int32(b) for p, b in zip(parts, base)]).astype(np.int32),
        colors=np.concatenate([p.colors for p in parts]),
        grade=np.concatenate([p.grade for p in parts]),
        source=np.concatenate([p.source for p in parts]),
        region=np.concatenate([p.region for p in parts]),
    )  # fmt: skip


def weld(lod: LodMesh) -> LodMesh:
    """Merge vertices with bit-identical positions (one of them gives the colour), drop faces that
    collapse and unused vertices. Vertices come out sorted by position; a texture (uv, atlas) is dropped.

    >>> p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]], np.float32)
    >>> w = weld(LodMesh(p, np.array([[0, 1, 2], [3, 2, 0]], np.int32), np.zeros((4, 3), np.uint8),
    ...                  np.zeros(2, np.int8), np.zeros(2, np.int8), np.zeros(2, np.int32)))
    >>> len(w.positions), w.faces.tolist()
    (3, [[0, 2, 1], [2, 1, 0]])
    """
    bits = lod.positions.view(np.uint32)
    order = _lexsort_xyz(bits)
    sb = bits[order]
    new_group = np.ones(len(sb), bool)
    new_group[1:] = (sb[1:] != sb[:-1]).any(axis=1)
    del sb
    remap = np.empty(len(order), np.int32)  # int32 like the faces: half the memory of int64
    remap[order] = np.cumsum(new_group, dtype=np.int32) - 1
    rep = order[new_group]  # first (in sorted order) vertex of each group
    del order, new_group
    faces = remap[lod.faces]
    del remap
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return _compact(LodMesh(lod.positions[rep], faces[keep], lod.colors[rep],
                            lod.grade[keep], lod.source[keep], lod.region[keep]))


def _lexsort_xyz(bits: np.ndarray) -> np.ndarray:
    """``np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))`` for (n, 3) uint32, in two stable sorts (by z, then by
    the 64-bit (x, y) key): the same order, about twice as fast."""
    xy = (bits[:, 0].astype(np.uint64) << np.uint64(32)) | bits[:, 1]
    by_z = np.argsort(bits[:, 2], kind="stable")
    return by_z[np.argsort(xy[by_z], kind="stable")]


def _compact(lod: LodMesh) -> LodMesh:
    mask = np.zeros(len(lod.positions), bool)
    mask[lod.faces.reshape(-1)] = True  # linear, no sort
    used = np.flatnonzero(mask)
    if len(used) == len(lod.positions):
        return lod
    remap = np.full(len(lod.positions), -1, np.int64)
    remap[used] = np.arange(len(used))
    return LodMesh(lod.positions[used], remap[lod.faces].astype(np.int32), lod.colors[used],
                   lod.grade, lod.source, lod.region, None if lod.uv is None else lod.uv[used], lod.atlas)


@dataclass(frozen=True)
class Decimation:
    """The simplified mesh and its measured deviation from the input (metres, sampled two-sided
    Hausdorff distance: max over points sampled on either surface of the distance to the other)."""

    mesh: LodMesh
    hausdorff_m: float
    mean_m: float


def sample_surface(positions: np.ndarray, faces: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float32 points uniformly distributed over the triangles' area (area-weighted faces,
    uniform barycentric coordinates)."""
    p = positions.astype(np.float64)
    a, b, c = p[faces[:, 0]], p[faces[:, 1]], p[faces[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    if area.sum() <= 0:
        return p[faces[:, 0]][:n].astype(np.float32)
    pick = rng.choice(len(faces), size=n, p=area / area.sum())
    r1, r2 = rng.random(n), rng.random(n)
    flip = r1 + r2 > 1
    r1[flip], r2[flip] = 1 - r1[flip], 1 - r2[flip]
    pts = a[pick] + r1[:, None] * (b[pick] - a[pick]) + r2[:, None] * (c[pick] - a[pick])
    return pts.astype(np.float32)


def _scene(positions: np.ndarray, faces: np.ndarray):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.ascontiguousarray(positions, np.float32)),
                        o3d.core.Tensor(np.ascontiguousarray(faces, np.uint32)))
    return scene


def _distances(scene, points: np.ndarray) -> np.ndarray:
    import open3d as o3d

    return scene.compute_distance(o3d.core.Tensor(np.ascontiguousarray(points, np.float32))).numpy()


def _quadric_fqmr(lod: LodMesh, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    import pyfqmr

    s = pyfqmr.Simplify()
    s.setMesh(lod.positions.astype(np.float64), lod.faces)
    s.simplify_mesh(target_count=int(target_faces), aggressiveness=7, preserve_border=True, verbose=False)
    v, f, _ = s.getMesh()
    return v.astype(np.float32), f.astype(np.int32)


def _quadric_pymeshlab(lod: LodMesh, target_faces: int) -> tuple[np.ndarray, np.ndarray]:
    try:
        import pymeshlab
    except ImportError:
        raise InputError(None, "decimator 'pymeshlab' needs pymeshlab (GPL), which is not installed: "
                               "pip install 'ms3d[gpl]', or set decimator to 'auto' (pyfqmr)") from None
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=lod.positions.astype(np.float64), face_matrix=lod.faces))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(target_faces), preserveboundary=True,
                                                boundaryweight=2.0, optimalplacement=True, autoclean=True)
    out = ms.current_mesh()
    return out.vertex_matrix().astype(np.float32), out.face_matrix().astype(np.int32)


def quadric_backend() -> str:
    """The default decimator: "fqmr" (pyfqmr, Fast Quadric Mesh Simplification, MIT; a dependency).
    "pymeshlab" (VCG through pymeshlab, GPL) is optional: the ``gpl`` extra."""
    return "fqmr"


MAX_BLOCK_FACES = 400_000  # faces decimated at once: pyfqmr needs ~530 bytes per face, the deviation ~400


def split_blocks(positions: np.ndarray, faces: np.ndarray, max_faces: int) -> list[np.ndarray]:
    """Face indices (int64, ascending) of ground blocks of at most ``max_faces`` faces each: the faces'
    centroids are split at the median of the block's longer horizontal side (x or y), recursively.

    positions: (n, 3) float32 ENU metres; faces: (m, 3) int.

    >>> p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [9, 0, 0], [10, 0, 0], [9, 1, 0]], np.float32)
    >>> [b.tolist() for b in split_blocks(p, np.array([[3, 4, 5], [0, 1, 2]]), 1)]
    [[1], [0]]
    """
    xy = positions[:, :2]
    cent = (xy[faces[:, 0]] + xy[faces[:, 1]] + xy[faces[:, 2]]) / np.float32(3)  # (m, 2) float32
    todo, out = [np.arange(len(faces))], []
    while todo:
        idx = todo.pop()
        if len(idx) <= max_faces:
            out.append(np.sort(idx))
            continue
        c = cent[idx]
        axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
        half = len(idx) // 2
        order = np.argpartition(c[:, axis], half)  # the median split in linear time
        todo += [idx[order[half:]], idx[order[:half]]]
    return out


def decimate(lod: LodMesh, target_faces: int, samples: int = 50_000, backend: str | None = None,
             max_block_faces: int = MAX_BLOCK_FACES) -> Decimation:
    """Quadric edge-collapse decimation to about ``target_faces``, open boundaries kept (tile borders
    stay where the neighbour expects them).

    backend: "fqmr" (pyfqmr, ~6x faster here) or "pymeshlab" (VCG; the optional ``gpl`` extra: without it
    a one-line :class:`InputError`); default ``quadric_backend()``.
    A new vertex takes the colour of the nearest input vertex; a new face the provenance of the input face
    whose centroid is nearest its centroid. The deviation is measured both ways
    (open3d ray-casting distances) at ``samples`` area-uniform points on each surface plus the
    simplified mesh's vertices.

    A mesh of more than ``max_block_faces`` faces is decimated block by block (:func:`split_blocks`),
    each to its share of ``target_faces`` and with its share of ``samples``, its borders kept like a
    tile's, then welded: memory is bounded by a block, not by the mesh. The deviation is then the max over
    blocks (a bound: a point of a block is no farther from the whole than from its block), the mean the
    face-weighted mean.
    """
    if lod.n_faces <= target_faces or lod.n_faces < 4:
        return Decimation(lod, 0.0, 0.0)
    if lod.n_faces <= max_block_faces:
        return _decimate_block(lod, target_faces, samples, backend)
    parts, shares = [], []
    for idx in split_blocks(lod.positions, lod.faces, max_block_faces):
        block = _compact(LodMesh(lod.positions, lod.faces[idx], lod.colors, lod.grade[idx], lod.source[idx],
                                 lod.region[idx]))
        shares.append(len(idx) / lod.n_faces)
        parts.append(_decimate_block(block, math.ceil(target_faces * shares[-1]),
                                     max(1000, math.ceil(samples * shares[-1])), backend))
        del block
    mesh = weld(concat_lods([d.mesh for d in parts]))
    return Decimation(mesh, max(d.hausdorff_m for d in parts), float(sum(d.mean_m * w for d, w in zip(parts, shares))))


def _decimate_block(lod: LodMesh, target_faces: int, samples: int, backend: str | None) -> Decimation:
    """:func:`decimate` of one block (the whole mesh at once)."""
    if lod.n_faces <= target_faces or lod.n_faces < 4:
        return Decimation(lod, 0.0, 0.0)
    backend = backend or quadric_backend()
    if backend not in ("fqmr", "pymeshlab"):
        raise ValueError(f"unknown decimator {backend!r}: 'fqmr' or 'pymeshlab'")
    positions, faces = (_quadric_fqmr if backend == "fqmr" else _quadric_pymeshlab)(lod, target_faces)
    if len(faces) == 0:
        return Decimation(lod, 0.0, 0.0)
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    # unbalanced trees: half the build time, the same nearest neighbours
    _, nearest_vertex = cKDTree(lod.positions, balanced_tree=False).query(positions, workers=1)
    colors = lod.colors[nearest_vertex]
    tree = cKDTree(face_centroids(lod.positions, lod.faces), balanced_tree=False)
    _, nearest = tree.query(face_centroids(positions, faces), workers=1)
    del tree
    to_original = _distances(_scene(lod.positions, lod.faces),
                             np.concatenate([positions, sample_surface(positions, faces, samples, rng)]))
    to_simplified = _distances(_scene(positions, faces), sample_surface(lod.positions, lod.faces, samples, rng))
    simplified = _compact(LodMesh(positions, faces, colors, lod.grade[nearest], lod.source[nearest], lod.region[nearest]))
    dist = np.concatenate([to_original, to_simplified])
    return Decimation(simplified, float(dist.max()), float(dist.mean()))


def face_centroids(positions: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(m, 3) float64 centroids of the faces (m, 3) over positions (n, 3) float32 (what
    ``positions[faces].astype(np.float64).mean(axis=1)`` gives, without its (m, 3, 3) temporaries)."""
    p = positions.astype(np.float64)
    return (p[faces[:, 0]] + p[faces[:, 1]] + p[faces[:, 2]]) / 3.0


def sample_colors(image: np.ndarray, uv_gltf: np.ndarray) -> np.ndarray:
    """(n, 3) uint8: the pixel of ``image`` (H, W, 3) uint8 nearest each (n, 2) uv (glTF convention,
    origin top-left), clamped to the image."""
    h, w = image.shape[:2]
    x = np.clip((uv_gltf[:, 0] * w).astype(np.int64), 0, w - 1)
    y = np.clip((uv_gltf[:, 1] * h).astype(np.int64), 0, h - 1)
    return image[y, x]
