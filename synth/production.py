"""The synth mesh written as a ContextCapture-style tiled production, and the cameras as a COLMAP text model.

Layout (``storage.formats.production`` reads it)::

    mesh/metadata.xml                                   SRS and SRSOrigin (written by synth.generate)
    mesh/Data/Tile_+000_+000/Tile_+000_+000.obj         one tile: OBJ + MTL + its own texture atlas
    mesh/Data/Tile_+000_+000/Tile_+000_+000_L17.obj     (optional) a coarser level; the finest is then
    mesh/Data/Tile_+000_+000/Tile_+000_+000_L18.obj     named _L18, and readers keep only it

Faces go to the tile of their centroid on a ``tile_m`` grid in mesh-local metres (tile (ix, iy) covers
``[ix tile_m, (ix + 1) tile_m)``); a vertex used by faces of several tiles is written into each of them from
the same float64 value, so its text is identical and the seam welds by exact position. No face is split or
moved: the tiles together hold exactly the faces of the mesh.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.formats.meshes import write_obj

FINEST_LEVEL = 18  # the level number of the finest LOD when a tile has several (ContextCapture-like)


@dataclass(frozen=True)
class ProductionTile:
    """One tile of the production. name: ``Tile_+XXX_+YYY``; rows: (k,) int64 indices of its faces in the
    source mesh, ascending (its face i is source face rows[i])."""

    name: str
    ix: int
    iy: int
    rows: np.ndarray


def tile_name(ix: int, iy: int) -> str:
    """ContextCapture tile folder name.

    >>> tile_name(1, -2)
    'Tile_+001_-002'
    """
    return f"Tile_{ix:+04d}_{iy:+04d}"


def split_tiles(vertices: np.ndarray, faces: np.ndarray, tile_m: float) -> list[ProductionTile]:
    """Faces by the ``tile_m`` ground tile of their centroid.

    vertices: (n, 3) float64 metres (mesh-local); faces: (m, 3) int64. Returns the non-empty tiles sorted by
    (ix, iy); every face is in exactly one of them.

    >>> v = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0], [60, 0, 0], [61, 0, 0], [60, 1, 0]])
    >>> [(t.name, t.rows.tolist()) for t in split_tiles(v, np.array([[3, 4, 5], [0, 1, 2]]), 50.0)]
    [('Tile_+000_+000', [1]), ('Tile_+001_+000', [0])]
    """
    cent = np.asarray(vertices, np.float64)[np.asarray(faces)].mean(axis=1)
    ij = np.floor(cent[:, :2] / float(tile_m)).astype(np.int64)
    keys, inverse = np.unique(ij, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    return [ProductionTile(tile_name(int(ix), int(iy)), int(ix), int(iy), np.flatnonzero(inverse == k))
            for k, (ix, iy) in enumerate(keys)]


def submesh(vertices: np.ndarray, faces: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (k, 3) float64, faces (r, 3) int64) of faces ``rows``: only the vertices they use, in
    ascending source order, values copied bit for bit.

    >>> v, f = submesh(np.arange(12.0).reshape(4, 3), np.array([[0, 1, 2], [1, 3, 2]]), np.array([1]))
    >>> v[:, 0].tolist(), f.tolist()
    ([3.0, 6.0, 9.0], [[0, 2, 1]])
    """
    f = np.asarray(faces, np.int64)[rows]
    used, local = np.unique(f, return_inverse=True)
    return np.asarray(vertices, np.float64)[used], local.reshape(-1, 3).astype(np.int64)


def cluster_decimate(vertices: np.ndarray, faces: np.ndarray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A coarser level of detail by vertex clustering: vertices in one ``cell_m`` cube merge at their mean;
    faces that collapse (two corners in one cell) and repeated faces are dropped.

    vertices: (n, 3) float64 metres; faces: (m, 3) int64 -> (vertices (k, 3) float64, faces (r, 3) int64).

    >>> v = np.array([[0., 0, 0], [0.1, 0, 0], [2, 0, 0], [0, 2, 0]])
    >>> _, f = cluster_decimate(v, np.array([[0, 2, 3], [1, 2, 3], [0, 1, 2]]), 1.0)
    >>> f.tolist()  # clusters in cell order: (0, 0, 0), (0, 2, 0), (2, 0, 0)
    [[0, 2, 1]]
    """
    cell = np.floor(np.asarray(vertices, np.float64) / float(cell_m)).astype(np.int64)
    _, cluster = np.unique(cell, axis=0, return_inverse=True)
    cluster = cluster.ravel()
    counts = np.bincount(cluster)
    mean = np.stack([np.bincount(cluster, vertices[:, a]) / counts for a in range(3)], axis=1)
    f = cluster[np.asarray(faces, np.int64)]
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])
    f = f[keep]
    _, uniq = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(uniq)]
    used, local = np.unique(f, return_inverse=True)
    return mean[used], local.reshape(-1, 3).astype(np.int64)


def write_production(mesh_root: Path, mvs, tile_m: float, rng: np.random.Generator, lod_tile: str | None = None,
                     lod_cell_m: float = 1.0) -> dict[str, tuple[str, np.ndarray]]:
    """Write ``mvs`` (a :class:`synth.scene.Mesh`, mesh-local metres) as ``mesh_root/Data/Tile_*/`` OBJ files,
    each with its own texture atlas (``synth.texture.bake_atlas``, drawn from ``rng`` tile after tile).

    lod_tile: the name of one tile that also gets a coarser level (:func:`cluster_decimate` at
    ``lod_cell_m``, untextured): its finest file is then ``<name>_L18.obj`` beside ``<name>_L17.obj``.
    Returns, per source face, where it went: {tile name: (path relative to ``mesh_root.parent``, rows)}.
    """
    from .scene import Mesh
    from .texture import bake_atlas

    out = {}
    for t in split_tiles(mvs.vertices, mvs.faces, tile_m):
        v, f = submesh(mvs.vertices, mvs.faces, t.rows)
        part = Mesh(v, f, mvs.face_class[t.rows], mvs.face_building[t.rows], mvs.face_color[t.rows])
        uv, atlases, face_atlas = bake_atlas(part, rng)
        folder = mesh_root / "Data" / t.name
        stem = f"{t.name}_L{FINEST_LEVEL}" if t.name == lod_tile else t.name
        write_obj(folder / f"{stem}.obj", v, f, uv=uv, texture_images=atlases, face_texture=face_atlas,
                  texture_format="jpg")
        if t.name == lod_tile:
            cv, cf = cluster_decimate(v, f, lod_cell_m)
            write_obj(folder / f"{t.name}_L{FINEST_LEVEL - 1}.obj", cv, cf,
                      face_colors=np.full((len(cf), 3), 170, np.uint8))
        out[t.name] = (str((folder / f"{stem}.obj").relative_to(mesh_root.parent)), t.rows)
    return out


def defect_faces_by_file(faces: list[int], tiles: dict[str, tuple[str, np.ndarray]]) -> dict[str, list[int]]:
    """A defect's source face indices -> {tile file: face indices in that file} (files in name order).

    >>> defect_faces_by_file([0, 5, 6], {"a": ("mesh/a.obj", np.array([1, 5])), "b": ("mesh/b.obj", np.array([0, 6]))})
    {'mesh/a.obj': [1], 'mesh/b.obj': [0, 1]}
    """
    f = np.asarray(faces, np.int64)
    out = {}
    for name in sorted(tiles):
        path, rows = tiles[name]
        hit = np.flatnonzero(np.isin(rows, f))
        if len(hit):
            out[path] = hit.tolist()
    return out


def write_colmap_model(folder: Path, cameras: list[dict], frame_origin) -> Path:
    """The synth cameras as a COLMAP sparse text model in ``folder`` (cameras.txt, images.txt and an empty
    points3D.txt), poses in world coordinates of the mesh frame, as the photogrammetry that made the mesh
    would deliver them.

    cameras: cameras.json-like entries {"image", "K", "R", "t", "width", "height", "dist"?} with
    ``X_cam = R (X_world - frame_origin) + t`` (mesh frame); written as ``X_cam = R X_world + (t - R o)``.
    Returns ``folder``.
    """
    from storage.formats.camera_files import write_colmap
    from storage.formats.cameras import Camera

    o = np.asarray(frame_origin, np.float64)
    cams = []
    for c in cameras:
        R = np.asarray(c["R"], np.float64)
        cams.append(Camera(c["image"], np.asarray(c["K"], np.float64), R, np.asarray(c["t"], np.float64) - R @ o,
                           int(c["width"]), int(c["height"]), np.asarray(c.get("dist", np.zeros(5)), np.float64)))
    write_colmap(folder, cams)
    (Path(folder) / "points3D.txt").write_text("# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[]\n")
    return Path(folder)
