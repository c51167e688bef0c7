"""GLB / glTF meshes through trimesh (``process=False``): glTF is Y-up by specification, so positions go
through each mesh node's world transform (node matrix or TRS, down the node hierarchy of the default scene),
then to Z-up as (x, y, z)_zup = (x, -z, y). Registered in :mod:`storage.formats.meshes`.
"""

from __future__ import annotations

import json
import re
import struct
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.mesh_data import MeshData


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


def read_gltf(path: Path) -> MeshData:
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


__all__ = ["read_gltf", "y_up_to_z_up"]
