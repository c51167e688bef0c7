"""Mesh readers (OBJ+MTL, PLY, GLB/glTF, folders of tiles) and OBJ / PLY writers.

Readers form a registry keyed by extension (``READERS``). Each returns the file's faces in file order,
after the same checks. They degrade where a user's tool would (trimesh, MeshLab): faces that touch a
NaN/inf vertex or index a vertex out of range are dropped, and a missing MTL or texture image leaves
its faces untextured, each with one line in ``MeshData.warnings`` naming the file and the counts
("dropped 3 of 134,116 faces: ..."). A file is refused with :class:`storage.errors.InputError` naming
it only when nothing usable remains: missing, empty, no (usable) faces, corrupt or truncated GLB.
Degenerate faces (a repeated vertex id, or area < 1e-12 m²) and duplicate faces (same three vertex
ids) are dropped and counted; non-manifold edges are only counted.

OBJ + MTL reading and writing live in :mod:`storage.formats.obj` (own parser, see there), ``MeshData`` and
the face checks in :mod:`storage.formats.mesh_data`; all are re-exported here. PLY and glTF go through trimesh
(``process=False``).

Coordinates: ``vertices`` are float64 WORLD metres = file coordinates * ``units_scale`` + ``offset``
(``offset`` is e.g. ContextCapture's SRSOrigin when the tiles are stored relative to it). glTF is Y-up
by specification: its positions go through each mesh node's world transform (node matrix or TRS, down
the node hierarchy of the default scene), then to Z-up as (x, y, z)_zup = (x, -z, y), before the offset.
UVs follow the OBJ convention (origin bottom-left, v up).
"""

from __future__ import annotations

import re
import struct
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path
from storage.errors import InputError
from storage.formats.mesh_data import (
    DEGENERATE_AREA_M2,
    MeshData,
    count_nonmanifold_edges,
    degenerate_faces,
    duplicate_faces,
    unusable_faces,
)
from storage.formats.obj import read_obj, write_obj
from storage.formats.production import finest_lod
from storage.inputs.remote import readable


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


# --- PLY and glTF through trimesh ------------------------------------------------------------------


def _read_ply(path: Path) -> MeshData:
    import trimesh

    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as err:
        raise InputError(path, f"unreadable PLY ({type(err).__name__}: {err})") from err
    if not isinstance(loaded, trimesh.Trimesh):
        raise InputError(path, "empty mesh (no faces; a point cloud?)")
    mesh = MeshData(
        vertices=np.asarray(loaded.vertices, np.float64), faces=np.asarray(loaded.faces, np.int64)
    )
    kind = loaded.visual.kind
    if kind == "face":
        mesh.face_colors = np.asarray(loaded.visual.face_colors)[:, :3].astype(np.uint8)
    elif kind == "vertex":
        mesh.vertex_colors = np.asarray(loaded.visual.vertex_colors)[:, :3].astype(np.uint8)
    return mesh


def _check_glb_header(path: Path) -> None:
    with open(path, "rb") as f:
        head = f.read(12)
    if len(head) < 12 or head[:4] != b"glTF":
        raise InputError(path, "not a GLB file (missing 'glTF' magic)")
    declared = struct.unpack("<I", head[8:12])[0]
    size = path.stat().st_size
    if size < declared:
        raise InputError(path, f"truncated GLB: header says {declared:,} bytes, file has {size:,}")


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", name)]


def y_up_to_z_up(xyz: np.ndarray) -> np.ndarray:
    """glTF's Y-up frame to ms3d's Z-up one: (x, y, z) -> (x, -z, y), a rotation of +90 deg about x.

    xyz: (n, 3) float64 -> (n, 3) float64.

    >>> y_up_to_z_up(np.array([[1.0, 2.0, 3.0]])).tolist()
    [[1.0, -3.0, 2.0]]
    """
    return np.stack([xyz[:, 0], -xyz[:, 2], xyz[:, 1]], axis=1)


def _gltf_json(path: Path) -> dict:
    """The JSON of a .gltf, or of a GLB's first chunk; {} if it cannot be parsed (trimesh then says why)."""
    import json

    try:
        if path.suffix.lower() == ".gltf":
            return json.loads(path.read_text())
        with open(path, "rb") as f:
            head = f.read(20)
            return json.loads(f.read(struct.unpack("<I", head[12:16])[0]))
    except (OSError, ValueError, struct.error):
        return {}


def _missing_gltf_images(path: Path) -> list[str]:
    """External image files (``images[].uri``, not data URIs) the glTF names that do not exist."""
    from urllib.parse import unquote

    uris = [im.get("uri", "") for im in _gltf_json(path).get("images") or []]
    return [u for u in uris if u and not u.startswith("data:") and not (path.parent / unquote(u)).is_file()]


def _read_gltf(path: Path) -> MeshData:
    """The meshes of the default scene, each through its node's world transform (trimesh's scene graph
    composes node matrices / TRS down the hierarchy), then Y-up -> Z-up; faces in node-name order."""
    import trimesh

    if path.suffix.lower() == ".glb":
        _check_glb_header(path)
    try:
        scene = trimesh.load_scene(str(path), process=False)
    except Exception as err:
        raise InputError(path, f"corrupt or truncated glTF ({type(err).__name__}: {err})") from err
    parts, images, n_untextured = [], {}, 0
    for node in sorted(scene.graph.nodes_geometry, key=_natural_key):
        transform, geom_name = scene.graph[node]
        geom = scene.geometry[geom_name]
        if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
            continue
        faces = np.asarray(geom.faces, np.int64)
        vertices = y_up_to_z_up(trimesh.transform_points(np.asarray(geom.vertices, np.float64), transform))
        part = MeshData(vertices=vertices, faces=faces)
        visual = geom.visual
        if visual.kind == "texture" and visual.uv is not None and len(visual.uv):
            part.uv = np.asarray(visual.uv, np.float32)[faces]
            material = visual.material
            image = getattr(material, "baseColorTexture", None) or getattr(material, "image", None)
            if image is not None:
                ref = images.setdefault(id(image), (f"{path.resolve()}#image{len(images)}", image))[0]
                part.textures = [ref]
                part.embedded_textures = {ref: np.asarray(image.convert("RGB"))}
                part.face_texture = np.zeros(len(faces), np.int16)
            else:
                n_untextured += len(faces)
        elif visual.kind == "face":
            part.face_colors = np.asarray(visual.face_colors)[:, :3].astype(np.uint8)
        elif visual.kind == "vertex":
            part.vertex_colors = np.asarray(visual.vertex_colors)[:, :3].astype(np.uint8)
        parts.append(part)
    mesh = MeshData.concat(parts)
    missing = _missing_gltf_images(path)
    if missing:  # trimesh reads such a file without the image; say so
        shown = ", ".join(missing[:3]) + (f" and {len(missing) - 3} more" if len(missing) > 3 else "")
        mesh.warnings.append(f"{path}: texture image {shown} (glTF images) not found; {n_untextured:,} of "
                             f"{mesh.n_faces:,} faces read untextured")
    return mesh


READERS: dict[str, Callable[[Path], MeshData]] = {
    ".obj": read_obj, ".ply": _read_ply, ".glb": _read_gltf, ".gltf": _read_gltf,
}  # fmt: skip


# --- public reading API ----------------------------------------------------------------------------


def read_mesh(path: str | Path, offset=(0.0, 0.0, 0.0), units_scale: float = 1.0) -> MeshData:
    """Read one mesh file (OBJ, PLY, GLB, glTF), or every mesh file under a folder, concatenated.

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
    return [Path(p) for p in finest_lod(found)[0]]


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
    with Image.open(readable(ref)) as image:
        return np.asarray(image.convert("RGB"))


# --- PLY writer ----------------------------------------------------------------------------------


def write_ply(
    path: str | Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    face_colors: np.ndarray | None = None,
    vertex_colors: np.ndarray | None = None,
) -> Path:
    """Binary little-endian PLY with float64 ('double') vertices, so world coordinates survive exactly.

    vertices: (n, 3) float64 metres; faces: (m, 3) int (written int32); colours: (m|n, 3) uint8.
    """
    path = Path(path)
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces)
    if len(faces) and (faces.min() < 0 or faces.max() >= len(vertices)):
        raise ValueError(f"{path}: face indices out of range for {len(vertices)} vertices")
    rgb = ["property uchar red", "property uchar green", "property uchar blue"]
    v_dtype = [("xyz", "<f8", 3)] + ([("rgb", "u1", 3)] if vertex_colors is not None else [])
    f_dtype = [("n", "u1"), ("ids", "<i4", 3)] + ([("rgb", "u1", 3)] if face_colors is not None else [])
    v_rec = np.zeros(len(vertices), v_dtype)
    v_rec["xyz"] = vertices
    f_rec = np.zeros(len(faces), f_dtype)
    f_rec["n"], f_rec["ids"] = 3, faces
    if vertex_colors is not None:
        v_rec["rgb"] = vertex_colors
    if face_colors is not None:
        f_rec["rgb"] = face_colors
    header = [
        "ply", "format binary_little_endian 1.0", f"element vertex {len(vertices)}",
        "property double x", "property double y", "property double z",
        *(rgb if vertex_colors is not None else []),
        f"element face {len(faces)}", "property list uchar int vertex_indices",
        *(rgb if face_colors is not None else []),
        "end_header",
    ]  # fmt: skip
    with atomic_path(path) as tmp, open(tmp, "wb") as out:
        out.write(("\n".join(header) + "\n").encode("ascii"))
        out.write(v_rec.tobytes())
        out.write(f_rec.tobytes())
    return path


__all__ = [
    "DEGENERATE_AREA_M2",
    "READERS",
    "MeshData",
    "count_nonmanifold_edges",
    "degenerate_faces",
    "duplicate_faces",
    "iter_meshes",
    "mesh_files",
    "read_mesh",
    "read_mesh_dir",
    "texture_image",
    "write_obj",
    "write_ply",
    "y_up_to_z_up",
]
