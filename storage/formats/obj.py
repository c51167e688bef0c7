"""OBJ + MTL: reading (own parser) and writing (OBJ, MTL and texture images beside it, atomically).

OBJ is parsed here rather than by trimesh: trimesh splits an OBJ by material and re-indexes vertices
on UV seams, whereas we keep the face order and count of the file, the per-corner UVs and the texture
*paths*. :func:`read_obj` returns the file's faces in file coordinates, unchecked; the public
``storage.formats.meshes.read_mesh`` validates them and moves them to world metres. UVs follow the OBJ
convention (origin bottom-left, v up).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path
from storage.errors import InputError
from storage.formats.mesh_data import MeshData
from storage.formats.mtl import apply_materials
from storage.formats.obj_statements import fast_statements, resolve_ids, seen_before_faces, slow_statements


def read_obj(path: Path) -> MeshData:
    """Faces (polygons fan-triangulated), per-corner UVs, vertex colours and MTL materials of an OBJ,
    in file order and file coordinates. A missing MTL or texture image, a face statement of fewer than 3
    vertices or texture coordinate ids out of range are worked around (untextured faces, no triangle),
    each with one line in ``MeshData.warnings``; vertex ids are checked by ``read_mesh``.

    Photogrammetry OBJs (blocks of v, vt and triangle f statements) are parsed block by block with a C
    CSV reader: 387 MB (2.9 M faces) in ~6 s against ~40 s line by line; any other OBJ line by line."""
    data = path.read_bytes()
    st = fast_statements(data)
    if st is None:
        st = slow_statements(path, data.decode(errors="replace"))
    xyzc, vt, counts, raw_v, raw_vt = st.xyzc, st.vt, st.counts, st.raw_v, st.raw_vt
    usemtl_names, faces_before_usemtl = st.usemtl_names, st.faces_before_usemtl
    if xyzc.shape[1] not in (3, 4, 6):
        raise InputError(path, f"malformed vertex statements ({xyzc.shape[1]} numbers each)")
    if vt.shape[1] > 2:
        vt = vt[:, :2]
    warnings = []
    if (counts < 3).any():  # such a statement gives no triangle (ntri 0 below)
        warnings.append(f"{path}: dropped {int((counts < 3).sum()):,} of {len(counts):,} face statements: "
                        "fewer than 3 vertices")
    negative = (raw_v < 0).any() or (raw_vt is not None and (raw_vt < 0).any())

    def seen(key: str) -> np.ndarray | None:
        return np.repeat(seen_before_faces(st.lines, key), counts) if negative else None

    v_idx = resolve_ids(raw_v, seen("v"))
    # fan-triangulate polygons: corners (s, s+j, s+j+1) for j = 1 .. c-2
    ntri = np.maximum(counts - 2, 0)
    tri_face = np.repeat(np.arange(len(counts)), ntri)
    j = np.arange(len(tri_face)) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    first = (np.cumsum(counts) - counts)[tri_face]
    corner = np.stack([first, first + j, first + j + 1], axis=1)
    mesh = MeshData(vertices=xyzc[:, :3], faces=v_idx[corner] if len(corner) else np.zeros((0, 3), np.int64),
                    warnings=warnings)
    if xyzc.shape[1] == 6:
        rgb = xyzc[:, 3:6]
        rgb = rgb * 255.0 if rgb.max() <= 1.0 else rgb  # 0..1 floats by convention, else 0..255
        mesh.vertex_colors = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    bad_uv = np.zeros(len(corner), bool)
    if raw_vt is not None:
        vt_idx = resolve_ids(raw_vt, seen("vt"))[corner]
        bad_uv = ((vt_idx >= len(vt)) | ((vt_idx < 0) & (raw_vt[corner] != 0))).any(axis=1)
        valid = (vt_idx >= 0) & ~bad_uv[:, None]  # corners without a vt get (0, 0)
        mesh.uv = np.zeros((*vt_idx.shape, 2), np.float32)
        mesh.uv[valid] = vt[vt_idx[valid]]
    material_ids: dict[str, int] = {}
    tri_mat = np.full(len(tri_face), -1, np.int64)
    if usemtl_names:
        ids = np.array([material_ids.setdefault(name, len(material_ids)) for name in usemtl_names] + [-1])
        run = np.searchsorted(faces_before_usemtl, np.arange(len(counts)), side="right") - 1
        tri_mat = ids[run][tri_face]  # run -1 (before any usemtl) picks the trailing -1
    apply_materials(path, mesh, st.mtllibs, material_ids, tri_mat)
    if bad_uv.any():  # the geometry is fine: only the texture of these faces is lost
        if mesh.face_texture is not None:
            mesh.face_texture[bad_uv] = -1
        mesh.warnings.append(f"{path}: {int(bad_uv.sum()):,} of {len(bad_uv):,} faces have texture coordinate "
                             f"ids out of range (the file has {len(vt):,} vt); read untextured")
    return mesh


# --- writer ---------------------------------------------------------------------------------------


def _format_rows(fmt: str, rows: np.ndarray, block: int = 100_000) -> Iterator[str]:
    for lo in range(0, len(rows), block):
        part = rows[lo : lo + block]
        yield (fmt * len(part)) % tuple(part.ravel().tolist())


def write_obj(
    path: str | Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    uv: np.ndarray | None = None,
    texture_images: Sequence[np.ndarray | str | Path] | None = None,
    face_texture: np.ndarray | None = None,
    face_colors: np.ndarray | None = None,
    offset=None,
    texture_format: str = "png",
) -> Path:
    """Write an OBJ with its MTL and texture images beside it, each atomically: images, then MTL, then OBJ.

    vertices: (n, 3) float64 world metres, written with 6 decimals (minus ``offset`` if given, so the
        file holds local coordinates; read back with ``read_mesh(path, offset=offset)``).
    faces: (m, 3) int64. uv: (m, 3, 2) per-corner (OBJ convention). texture_images: (H, W, 3|4) uint8
        arrays (written as PNG) or image paths (copied), named ``<stem>_tex<k>.<ext>``.
    face_texture: (m,) index into texture_images, -1 for none (default: all 0 when there is one image).
    face_colors: (m, 3) uint8 for untextured faces (one material per distinct colour).
    Face order is kept; one ``usemtl`` per run of faces sharing a material.
    """
    path = Path(path)
    vertices = np.asarray(vertices, np.float64)
    faces = np.asarray(faces, np.int64)
    m = len(faces)
    texture_images = list(texture_images or [])
    if face_texture is None:
        face_texture = np.zeros(m, np.int64) if len(texture_images) == 1 else np.full(m, -1, np.int64)
    face_texture = np.asarray(face_texture, np.int64)
    if len(face_texture) != m or (face_texture >= len(texture_images)).any():
        raise ValueError(f"{path}: face_texture must be (m,) with values < {len(texture_images)} or -1")

    names = _write_textures(path, texture_images, texture_format)
    # material code per face: a texture index, else a distinct colour, else the default material
    code = face_texture.copy()
    mtl_lines = [f"newmtl tex{k}\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {n}\n" for k, n in enumerate(names)]
    material_names = [f"tex{k}" for k in range(len(names))]
    plain = code < 0
    if plain.any():
        colours = np.full((int(plain.sum()), 3), 200, np.uint8)
        if face_colors is not None:
            colours = np.asarray(face_colors, np.uint8)[plain]
        unique, inverse = np.unique(colours, axis=0, return_inverse=True)
        code[plain] = len(names) + inverse.ravel()
        for rgb in unique:
            name = "col_{:02x}{:02x}{:02x}".format(*rgb)
            material_names.append(name)
            kd = " ".join(f"{c / 255:.6f}" for c in rgb)
            mtl_lines.append(f"newmtl {name}\nKd {kd}\nillum 1\n")
    use_mtl = bool(names) or face_colors is not None
    mtl_path = path.with_suffix(".mtl")
    if use_mtl:
        with atomic_path(mtl_path) as tmp:
            tmp.write_text("\n".join(mtl_lines))

    local = vertices - (np.asarray(offset, np.float64) if offset is not None else 0.0)
    with atomic_path(path) as tmp, open(tmp, "w") as out:
        out.write("# ms3d\n")
        if use_mtl:
            out.write(f"mtllib {mtl_path.name}\n")
        out.writelines(_format_rows("v %.6f %.6f %.6f\n", local))
        if uv is not None:
            out.writelines(_format_rows("vt %.7f %.7f\n", np.asarray(uv, np.float64).reshape(-1, 2)))
        ids = faces + 1
        if uv is not None:
            vt_ids = np.arange(1, 3 * m + 1, dtype=np.int64).reshape(m, 3)
            rows, fmt = np.stack([ids, vt_ids], axis=2).reshape(m, 6), "f %d/%d %d/%d %d/%d\n"
        else:
            rows, fmt = ids, "f %d %d %d\n"
        starts = np.flatnonzero(np.diff(code, prepend=-2)) if m else np.zeros(0, np.int64)
        for lo, hi in zip(starts, [*starts[1:], m]):
            if use_mtl:
                out.write(f"usemtl {material_names[code[lo]]}\n")
            out.writelines(_format_rows(fmt, rows[lo:hi]))
    return path


def _write_textures(path: Path, images: list, fmt: str = "png") -> list[str]:
    """Write texture images beside ``path``: arrays as PNG (lossless) or JPEG (quality 90, as
    photogrammetry packages deliver them; much faster for large atlases); paths are copied."""
    from PIL import Image

    names = []
    for k, image in enumerate(images):
        if isinstance(image, (str, Path)):
            name = f"{path.stem}_tex{k}{Path(image).suffix.lower()}"
            with atomic_path(path.parent / name) as tmp:
                shutil.copyfile(image, tmp)
        else:
            ext = "jpg" if fmt.lower() in ("jpg", "jpeg") else "png"
            name = f"{path.stem}_tex{k}.{ext}"
            opts = {"format": "JPEG", "quality": 90} if ext == "jpg" else {"format": "PNG", "compress_level": 3}
            with atomic_path(path.parent / name) as tmp:
                Image.fromarray(np.asarray(image, np.uint8)).save(tmp, **opts)
        names.append(name)
    return names


__all__ = ["read_obj", "write_obj"]
