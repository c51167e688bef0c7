"""Levels of detail for export: vertex-coloured meshes in ENU, quadric decimation, measured deviation.

A :class:`LodMesh` is what a quadtree node passes to its parent: float32 ENU positions (z-up), faces,
sRGB vertex colours (textures sampled at the vertices) and per-face provenance. Each node passes up
``decimate(content, content_faces / 4)``; a parent's content is its children's passed-up meshes welded
together. The deviation of each decimation is measured (sampled two-sided Hausdorff distance, pymeshlab)
so a parent's ``geometricError`` is a measured bound of its distance to the full-resolution leaves:
``max over children (hausdorff(child content, child passed-up) + child geometricError)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path


@dataclass(frozen=True, eq=False)
class LodMesh:
    """positions: (n, 3) float32 metres ENU (z up). faces: (m, 3) int32. colors: (n, 3) uint8 sRGB.
    grade / source: (m,) int8, region: (m,) int32 (see storage.tile_mesh)."""

    positions: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    grade: np.ndarray
    source: np.ndarray
    region: np.ndarray

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) (3,) float64 of the positions used by faces."""
        used = self.positions[np.unique(self.faces)] if self.n_faces else self.positions
        return used.min(axis=0).astype(np.float64), used.max(axis=0).astype(np.float64)


_FIELDS = ("positions", "faces", "colors", "grade", "source", "region")


def save_lod(path: str | Path, lod: LodMesh) -> None:
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(f, **{k: getattr(lod, k) for k in _FIELDS})


def load_lod(path: str | Path) -> LodMesh:
    with np.load(path, allow_pickle=False) as z:
        return LodMesh(**{k: z[k] for k in _FIELDS})


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
    """Merge vertices with bit-identical positions (the first one's colour wins), drop faces that
    collapse and unused vertices.

    >>> p = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0]], np.float32)
    >>> w = weld(LodMesh(p, np.array([[0, 1, 2], [3, 2, 0]], np.int32), np.zeros((4, 3), np.uint8),
    ...                  np.zeros(2, np.int8), np.zeros(2, np.int8), np.zeros(2, np.int32)))
    >>> len(w.positions), w.faces.tolist()
    (3, [[0, 1, 2], [1, 2, 0]])
    """
    bits = lod.positions.view(np.uint32)
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))
    sb = bits[order]
    new_group = np.ones(len(sb), bool)
    new_group[1:] = (sb[1:] != sb[:-1]).any(axis=1)
    group_of_sorted = np.cumsum(new_group) - 1
    remap = np.empty(len(order), np.int64)
    remap[order] = group_of_sorted
    rep = order[new_group]  # first (in sorted order) vertex of each group
    faces = remap[lod.faces]
    keep = (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    return _compact(LodMesh(lod.positions[rep], faces[keep].astype(np.int32), lod.colors[rep],
                            lod.grade[keep], lod.source[keep], lod.region[keep]))


def _compact(lod: LodMesh) -> LodMesh:
    used = np.unique(lod.faces)
    if len(used) == len(lod.positions):
        return lod
    remap = np.full(len(lod.positions), -1, np.int64)
    remap[used] = np.arange(len(used))
    return LodMesh(lod.positions[used], remap[lod.faces].astype(np.int32), lod.colors[used],
                   lod.grade, lod.source, lod.region)


@dataclass(frozen=True)
class Decimation:
    """The simplified mesh and its measured deviation from the input (metres, sampled two-sided
    Hausdorff distance: max over points sampled on either surface of the distance to the other)."""

    mesh: LodMesh
    hausdorff_m: float
    mean_m: float


def decimate(lod: LodMesh, target_faces: int, samples: int = 50_000) -> Decimation:
    """Quadric edge-collapse decimation (pymeshlab) to about ``target_faces``, keeping open boundaries
    (tile borders stay where the neighbour tile expects them), vertex colours carried by the surviving
    vertices, provenance taken from the nearest input face (by centroid). Deviation measured both ways
    with ``samples`` points per direction (plus the vertices of the simplified mesh).
    """
    import pymeshlab
    from scipy.spatial import cKDTree

    if lod.n_faces <= target_faces or lod.n_faces < 4:
        return Decimation(lod, 0.0, 0.0)
    ms = pymeshlab.MeshSet()
    rgba = np.ones((len(lod.positions), 4))
    rgba[:, :3] = lod.colors / 255.0
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=lod.positions.astype(np.float64), face_matrix=lod.faces,
                               v_color_matrix=rgba))
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=lod.positions.astype(np.float64), face_matrix=lod.faces,
                               v_color_matrix=rgba))
    ms.set_current_mesh(1)
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(target_faces), preserveboundary=True,
                                                boundaryweight=2.0, optimalplacement=True, autoclean=True)
    out = ms.current_mesh()
    positions = out.vertex_matrix().astype(np.float32)
    faces = out.face_matrix().astype(np.int32)
    colors = np.clip(np.round(out.vertex_color_matrix()[:, :3] * 255), 0, 255).astype(np.uint8)
    a = ms.get_hausdorff_distance(sampledmesh=0, targetmesh=1, samplevert=False, sampleface=True, samplenum=samples)
    b = ms.get_hausdorff_distance(sampledmesh=1, targetmesh=0, samplevert=True, sampleface=True, samplenum=samples)
    centroids_in = lod.positions[lod.faces].astype(np.float64).mean(axis=1)
    centroids_out = positions[faces].astype(np.float64).mean(axis=1)
    _, nearest = cKDTree(centroids_in).query(centroids_out, workers=1)
    simplified = _compact(LodMesh(positions, faces, colors, lod.grade[nearest], lod.source[nearest],
                                  lod.region[nearest]))
    return Decimation(simplified, float(max(a["max"], b["max"])), float(max(a["mean"], b["mean"])))


def sample_colors(image: np.ndarray, uv_gltf: np.ndarray) -> np.ndarray:
    """(n, 3) uint8: the pixel of ``image`` (H, W, 3) uint8 nearest each (n, 2) uv (glTF convention,
    origin top-left), clamped to the image."""
    h, w = image.shape[:2]
    x = np.clip((uv_gltf[:, 0] * w).astype(np.int64), 0, w - 1)
    y = np.clip((uv_gltf[:, 1] * h).astype(np.int64), 0, h - 1)
    return image[y, x]
