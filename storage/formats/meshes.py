"""Mesh readers (OBJ+MTL, PLY, GLB/glTF, 3MX/3MXB, 3D Tiles ``tileset.json``, folders of tiles) and OBJ / PLY
writers. A tileset's vertices are ECEF metres (:mod:`storage.formats.tiles3d`; placed into the campus CRS by
the scan and ingest stages); a ``.json`` is read only when named, never picked up from a folder.

Readers form a registry keyed by extension (``READERS``). Each returns the file's faces in file order,
after the same checks. They degrade where a user's tool would (trimesh, MeshLab): faces that touch a
NaN/inf vertex or index a vertex out of range are dropped, and a missing MTL or texture image leaves
its faces untextured, each with one line in ``MeshData.warnings`` naming the file and the counts
("dropped 3 of 134,116 faces: ..."). A file is refused with :class:`storage.errors.InputError` naming
it only when nothing usable remains: missing, empty, no (usable) faces, corrupt or truncated GLB.
Degenerate faces (a repeated vertex id, or area < 1e-12 m²) and duplicate faces (same three vertex
ids) are dropped and counted; non-manifold edges are only counted.

Each format has its module: :mod:`storage.formats.obj` (+ ``mtl``, ``obj_statements``; own parser),
:mod:`storage.formats.ply` and :mod:`storage.formats.gltf` (through trimesh, ``process=False``); this module is
their registry and the public API. ``MeshData`` and the face checks live in :mod:`storage.formats.mesh_data`.

Coordinates: ``vertices`` are float64 WORLD metres = file coordinates * ``units_scale`` + ``offset``
(``offset`` is e.g. ContextCapture's SRSOrigin when the tiles are stored relative to it). glTF is Y-up
by specification: its positions go through each mesh node's world transform (node matrix or TRS, down
the node hierarchy of the default scene), then to Z-up as (x, y, z)_zup = (x, -z, y), before the offset.
UVs follow the OBJ convention (origin bottom-left, v up).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.gltf import read_gltf, y_up_to_z_up
from storage.formats.mesh_data import (
    DEGENERATE_AREA_M2,
    MeshData,
    count_nonmanifold_edges,
    degenerate_faces,
    duplicate_faces,
    unusable_faces,
)
from storage.formats.obj import read_obj, write_obj
from storage.formats.ply import read_ply_mesh, write_ply
from storage.formats.production import finest_lod
from storage.formats.threemx import read_3mx, select_3mx
from storage.formats.tiles3d import read_tileset


def _drop_unusable(path: Path, mesh: MeshData) -> MeshData:
    """Drop the faces that index vertices out of range or touch a NaN/inf vertex, with one warning line;
    InputError when no face is left. The non-finite vertices, then unreferenced, are set to a kept
    face's first vertex, so vertex indices (and ids) stay those of the file and every vertex is finite."""
    v, f = mesh.vertices, mesh.faces
    if len(f) == 0:
        raise InputError(path, "empty mesh (no faces)")
    out, nan = unusable_faces(v, f)
    if not (out.any() or nan.any()):
        return mesh
    n_nan_v = int((~np.isfinite(v).all(axis=1)).sum())
    why = ([f"{int(nan.sum()):,} touch NaN or infinite vertices ({n_nan_v:,} of {len(v):,} vertices)"]
           if nan.any() else [])
    if out.any():
        first = int(np.flatnonzero(out)[0])
        why.append(f"{int(out.sum()):,} index vertices out of range (the mesh has {len(v):,} vertices; first "
                   f"bad face #{first} = {f[first].tolist()})")
    keep = ~(out | nan)
    if not keep.any():
        raise InputError(path, f"no usable face: of {len(f):,} faces " + " and ".join(why))
    mesh = mesh.select_faces(keep)
    if n_nan_v:
        mesh.vertices = np.where(np.isfinite(v).all(axis=1)[:, None], v, v[mesh.faces[0, 0]])
    mesh.warnings = [*mesh.warnings, f"{path}: dropped {int((~keep).sum()):,} of {len(f):,} faces: " + "; ".join(why)]
    return mesh


def _finish(path: Path, mesh: MeshData, offset, units_scale: float) -> MeshData:
    """Validate a mesh in file coordinates, move it to world metres, drop and count bad faces."""
    mesh = _drop_unusable(path, mesh)
    n_usable = mesh.n_faces
    mesh.vertices = mesh.vertices * float(units_scale) + np.asarray(offset, dtype=np.float64)
    degenerate = degenerate_faces(mesh.vertices, mesh.faces)
    mesh = mesh.select_faces(~degenerate)
    duplicate = duplicate_faces(mesh.faces)
    mesh = mesh.select_faces(~duplicate)
    if mesh.n_faces == 0:
        raise InputError(path, f"all {n_usable:,} faces are degenerate or duplicates")
    mesh.n_degenerate_dropped = int(degenerate.sum())
    mesh.n_duplicate_dropped = int(duplicate.sum())
    mesh.n_nonmanifold_edges = count_nonmanifold_edges(mesh.faces)
    mesh.source = str(path)
    return mesh


READERS: dict[str, Callable[[Path], MeshData]] = {
    ".obj": read_obj, ".ply": read_ply_mesh, ".glb": read_gltf, ".gltf": read_gltf, ".3mx": read_3mx,
    ".3mxb": read_3mx, ".json": read_tileset,
}  # fmt: skip


# --- public reading API ----------------------------------------------------------------------------


def read_mesh(path: str | Path, offset=(0.0, 0.0, 0.0), units_scale: float = 1.0) -> MeshData:
    """Read one mesh file (OBJ, PLY, GLB, glTF, a 3MX scene or root node), or every mesh file under a folder,
    concatenated.

    vertices = file coordinates * units_scale + offset, float64 world metres.
    """
    path = Path(path)
    if path.is_dir():
        return read_mesh_dir(path, offset, units_scale)
    if not path.exists():
        raise InputError(path, "file not found")
    reader = READERS.get(path.suffix.lower())
    if reader is None:
        supported = ", ".join(sorted(READERS))
        raise InputError(path, f"unsupported mesh format {path.suffix!r}; supported: {supported}")
    if path.stat().st_size == 0:
        raise InputError(path, "empty file (0 bytes)")
    return _finish(path, reader(path), offset, units_scale)


def mesh_files(folder: str | Path) -> list[Path]:
    """Mesh files under ``folder`` (recursively, sorted; hidden and temporary files skipped); of a tiled
    production, only the finest level of detail of each tile (:func:`storage.formats.production.finest_lod`), as
    input discovery reads it."""
    folder = Path(folder)
    found = sorted(
        str(p) for p in folder.rglob("*")
        if p.is_file() and p.suffix.lower() in READERS and not p.name.startswith(".")
    )  # fmt: skip
    return [Path(p) for p in finest_lod(select_3mx(found)[0])[0]]


def iter_meshes(path: str | Path, offset=(0.0, 0.0, 0.0), units_scale: float = 1.0) -> Iterator[MeshData]:
    """One MeshData per mesh file (a ContextCapture-style folder of tiles, or a single file), so memory
    is bounded by the largest tile."""
    path = Path(path)
    if not path.is_dir():
        yield read_mesh(path, offset, units_scale)
        return
    files = mesh_files(path)
    if not files:
        raise InputError(path, f"no mesh files ({', '.join(sorted(READERS))}) in this folder")
    for file in files:
        yield read_mesh(file, offset, units_scale)


def read_mesh_dir(folder: str | Path, offset=(0.0, 0.0, 0.0), units_scale: float = 1.0) -> MeshData:
    """All mesh files under ``folder`` as one MeshData (see ``iter_meshes`` for bounded memory)."""
    return MeshData.concat(iter_meshes(folder, offset, units_scale), source=str(folder))


def texture_image(mesh: MeshData, index: int) -> np.ndarray:
    """Pixels of ``mesh.textures[index]``: (H, W, 3) uint8."""
    from PIL import Image

    ref = mesh.textures[index]
    if ref in mesh.embedded_textures:
        return mesh.embedded_textures[ref]
    from storage.formats.embedded import resolve_ref

    with Image.open(resolve_ref(ref)) as image:
        return np.asarray(image.convert("RGB"))


def raw_vertices(path: str | Path) -> np.ndarray:
    """Vertex positions of a mesh file that failed validation: the ``v`` lines of an OBJ (whatever its
    faces say), else whatever trimesh can load. (n, 3) float64, possibly empty."""
    path = Path(path)
    if path.suffix.lower() == ".obj":
        rows = []
        with open(path, errors="replace") as f:
            for line in f:  # the error path only: a Python loop is fine here
                if line.startswith("v "):
                    parts = line.split()[1:4]
                    try:
                        rows.append([float(p) for p in parts])
                    except ValueError:
                        continue
        return np.asarray(rows, np.float64).reshape(-1, 3)
    import trimesh

    return np.asarray(trimesh.load(path, process=False, force="mesh").vertices, np.float64)


__all__ = [
    "DEGENERATE_AREA_M2",
    "READERS",
    "MeshData",
    "count_nonmanifold_edges",
    "degenerate_faces",
    "duplicate_faces",
    "iter_meshes",
    "mesh_files",
    "raw_vertices",
    "read_mesh",
    "read_mesh_dir",
    "texture_image",
    "write_obj",
    "write_ply",
    "y_up_to_z_up",
]
