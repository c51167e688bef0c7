"""MTL material libraries of an OBJ: reading them and applying their textures and colours to a mesh
(the OBJ itself: :mod:`storage.formats.obj`)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.formats.mesh_data import MeshData

_MAP_OPTION_ARGS = {"-blendu": 1, "-blendv": 1, "-cc": 1, "-clamp": 1, "-texres": 1, "-bm": 1, "-boost": 1,
                    "-imfchan": 1, "-mm": 2, "-o": 3, "-s": 3, "-t": 3}  # fmt: skip


def map_file_name(args: str) -> str:
    """The file name of a ``map_Kd [options] file`` statement (options skipped, spaces in names kept)."""
    words = args.split()
    i = 0
    while i < len(words) and words[i] in _MAP_OPTION_ARGS:
        n = _MAP_OPTION_ARGS[words[i]]
        i += 1
        while n and i < len(words) and re.fullmatch(r"[-+.\deE]+", words[i]):
            i, n = i + 1, n - 1
    return " ".join(words[i:]).replace("\\", "/")


@dataclass(frozen=True)
class Material:
    """A material of an MTL library: its ``map_Kd`` texture image (resolved path) and ``Kd`` colour (0..1)."""

    texture: Path | None
    kd: tuple[float, float, float] | None


def read_mtl(obj: Path, mtl: Path) -> dict[str, Material]:
    """The materials of the MTL library ``mtl`` (of the OBJ ``obj``), by name, in definition order."""
    materials, name, tex, kd = {}, None, None, None
    for line in mtl.read_text(errors="replace").replace("\t", " ").splitlines():
        key, _, rest = line.strip().partition(" ")
        if key == "newmtl":
            if name is not None:
                materials[name] = Material(tex, kd)
            name, tex, kd = rest.strip(), None, None
        elif key == "map_Kd" and rest.strip():
            tex = (mtl.parent / map_file_name(rest)).resolve()
        elif key == "Kd":
            kd = tuple(float(x) for x in rest.split()[:3])
    if name is not None:
        materials[name] = Material(tex, kd)
    return materials


def _names(paths: list, at_most: int = 3) -> str:
    shown = ", ".join(str(p) for p in paths[:at_most])
    return shown + (f" and {len(paths) - at_most} more" if len(paths) > at_most else "")


def apply_materials(path: Path, mesh: MeshData, mtllibs: list[str], material_ids: dict, tri_mat: np.ndarray):
    """Per-face texture index and (for untextured materials) face colours from the MTL libraries.

    A missing library or texture image does not fail the mesh: the faces of the materials it would
    have given are read untextured (a material whose image is missing keeps its ``Kd`` colour, if any;
    a material no library defines gets no colour), and one line per kind of problem, naming the files
    and the number of faces, is appended to ``mesh.warnings``.
    """
    materials: dict[str, Material] = {}
    missing_libs = []
    for lib in mtllibs:
        candidates = [lib] if (path.parent / lib).exists() else lib.split()
        for name in candidates:
            mtl = path.parent / name
            if mtl.is_file():
                materials.update(read_mtl(path, mtl))
            else:
                missing_libs.append(mtl)
    undefined = [mid for name, mid in material_ids.items() if name not in materials]
    if missing_libs:
        n = int(np.isin(tri_mat, undefined).sum()) if material_ids else 0
        mesh.warnings.append(f"{path}: material library {_names(missing_libs)} (mtllib) not found; "
                             f"{n:,} of {len(tri_mat):,} faces read untextured")
    if not material_ids:
        return
    textures: dict[Path, int] = {}
    tex_of_material = np.full(len(material_ids) + 1, -1, np.int16)  # last slot: faces before any usemtl
    kd_of_material = np.full((len(material_ids) + 1, 3), 255, np.uint8)
    needs_colour = False
    missing_images, n_untextured = [], 0
    mtl_order = {name: i for i, name in enumerate(materials)}
    # textures are numbered in MTL definition order, so write_obj's tex<k> read back as k
    for name in sorted(material_ids, key=lambda n: mtl_order.get(n, len(mtl_order))):
        mid = material_ids[name]
        mat = materials.get(name, Material(None, None))
        used = bool((tri_mat == mid).any())
        if mat.texture is not None and mat.texture.is_file():
            tex_of_material[mid] = textures.setdefault(mat.texture, len(textures))
        elif mat.texture is not None:
            if mat.texture not in missing_images:
                missing_images.append(mat.texture)
            n_untextured += int((tri_mat == mid).sum())
            needs_colour |= used and mat.kd is not None
        else:
            needs_colour |= used and name in materials
        if mat.kd is not None:
            kd_of_material[mid] = np.clip(np.round(np.array(mat.kd) * 255), 0, 255)
    if missing_images:
        mesh.warnings.append(f"{path}: texture image {_names(missing_images)} (map_Kd) not found; "
                             f"{n_untextured:,} of {len(tri_mat):,} faces read untextured")
    mesh.textures = [str(t) for t in textures]
    if textures:
        mesh.face_texture = tex_of_material[tri_mat]
    if needs_colour:
        mesh.face_colors = kd_of_material[tri_mat]
