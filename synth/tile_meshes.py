"""Stand-in merge output for export tests and benchmarks: a mesh cut into ground tiles with faked provenance.

Until the merge stage exists, ``fake_merged_workdir`` turns a synth campus mesh into what merge will
write: ``campus.json`` plus ``tiles/{ix}_{iy}/merged.npz`` per ground tile (faces routed by centroid),
with some blobs of faces marked bad, some of those marked rebuilt (untextured, vertex-coloured, with
a region id) and a few marked unknown.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.contracts.tile_mesh import (
    GRADE_BAD,
    GRADE_GOOD,
    GRADE_UNKNOWN,
    SOURCE_REBUILT,
    TileMesh,
    write_tile_mesh,
)
from storage.formats.meshes import MeshData
from storage.frame import CampusFrame
from storage.workdir.layout import WorkDir, write_campus
from tasks.geometry.tiling import group_by_tile


def per_vertex_uv(faces: np.ndarray, corner_uv: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Split vertices at texture seams.

    faces: (m, 3) int64; corner_uv: (m, 3, 2) float32. Returns (faces (m, 3) int64 into the new
    vertices, source vertex of each new vertex (k,) int64, uv (k, 2) float32): one new vertex per
    distinct (vertex, uv) pair.

    >>> f, src, uv = per_vertex_uv(np.array([[0, 1, 2], [0, 2, 3]]), np.zeros((2, 3, 2), np.float32))
    >>> f.tolist(), src.tolist()
    ([[0, 1, 2], [0, 2, 3]], [0, 1, 2, 3])
    """
    bits = np.ascontiguousarray(corner_uv.reshape(-1, 2)).view(np.uint32).astype(np.int64)
    key = np.stack([faces.reshape(-1), bits[:, 0], bits[:, 1]], axis=1)
    uniq, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    uv = corner_uv.reshape(-1, 2)[first]
    return inverse.reshape(-1, 3).astype(np.int64), uniq[:, 0], uv.astype(np.float32)


def fake_provenance(centroids: np.ndarray, rng: np.random.Generator, n_regions: int = 6, radius_m: float = 4.0
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(grade, source, region) per face for faces with ``centroids`` (m, 3): ``n_regions`` balls of
    ``radius_m`` around random faces are graded bad, the first half of them rebuilt (source 1, region
    id = ball number); 2 % of the other faces are graded unknown."""
    m = len(centroids)
    grade = np.full(m, GRADE_GOOD, np.int8)
    source = np.zeros(m, np.int8)
    region = np.full(m, -1, np.int32)
    centres = centroids[rng.choice(m, size=min(n_regions, m), replace=False)]
    for r, c in enumerate(centres):
        inside = np.linalg.norm(centroids - c, axis=1) < radius_m
        grade[inside] = GRADE_BAD
        if r < (len(centres) + 1) // 2:
            source[inside] = SOURCE_REBUILT
            region[inside] = r
    unknown = (rng.random(m) < 0.02) & (grade == GRADE_GOOD)
    grade[unknown] = GRADE_UNKNOWN
    return grade, source, region


def cut_tiles(mesh: MeshData, frame: CampusFrame, tile_size_m: float, rng: np.random.Generator) -> list[TileMesh]:
    """TileMeshes of ``mesh`` (world float64 vertices, per-corner uv) cut by face centroid into ground
    tiles of ``tile_size_m`` (campus-local). Rebuilt faces lose their texture and get vertex colours."""
    local = frame.to_local(mesh.vertices)
    centroids = local[mesh.faces].mean(axis=1)
    grade, source, region = fake_provenance(centroids, rng)
    face_texture = (mesh.face_texture if mesh.face_texture is not None else np.full(mesh.n_faces, -1)).astype(np.int16)
    face_texture = np.where(source == SOURCE_REBUILT, -1, face_texture).astype(np.int16)
    ij = np.floor(centroids[:, :2] / tile_size_m).astype(np.int64)
    out = []
    for tile, rows in group_by_tile(ij):
        faces = mesh.faces[rows]
        uv = mesh.uv[rows] if mesh.uv is not None else np.zeros((len(rows), 3, 2), np.float32)
        new_faces, src, vuv = per_vertex_uv(faces, uv)
        v = local[src]
        shade = np.clip(120 + 8 * v[:, 2], 0, 255).astype(np.uint8)  # rebuilt faces: a height ramp
        colors = np.stack([shade // 2, shade // 2 + 40, shade], axis=1).astype(np.uint8)
        out.append(TileMesh(
            tile=tile.key, vertices=v.astype(np.float32), faces=new_faces.astype(np.int32), uv=vuv,
            face_texture=face_texture[rows], textures=list(mesh.textures), vertex_colors=colors,
            grade=grade[rows], source=source[rows], region=region[rows],
        ))  # fmt: skip
    return out


def fake_merged_workdir(mesh: MeshData, frame: CampusFrame, work_dir: str | Path, tile_size_m: float = 50.0,
                        seed: int = 0) -> WorkDir:
    """Write ``campus.json`` and one ``tiles/{key}/merged.*`` per ground tile of ``mesh``; returns the WorkDir."""
    wd = WorkDir(work_dir)
    write_campus(wd, frame, {"matrix": np.eye(4).tolist(), "scale": 1.0}, {"tiling": {"tile_size_m": tile_size_m}})
    for tm in cut_tiles(mesh, frame, tile_size_m, np.random.default_rng(seed)):
        write_tile_mesh(wd.root / "tiles" / tm.tile, tm)
    return wd


def read_production(mesh_root: str | Path):
    """(MeshData in world metres, SRSOrigin (3,) tuple) of a synth mesh folder: every finest-LOD file of the
    production ``mesh_root`` (its tiles concatenated; seam vertices stay doubled), placed by its
    ``metadata.xml``."""
    from storage.formats.meshes import mesh_files, read_mesh
    from storage.formats.production import read_metadata

    origin = read_metadata(Path(mesh_root) / "metadata.xml").origin
    files = [str(p) for p in mesh_files(mesh_root)]  # the finest level of each tile
    return MeshData.concat([read_mesh(f, offset=origin) for f in files], source=str(mesh_root)), origin
