"""OBJ + MTL: reading (own parser) and writing (OBJ, MTL and texture images beside it, atomically).

OBJ is parsed here rather than by trimesh: trimesh splits an OBJ by material and re-indexes vertices
on UV seams, whereas we keep the face order and count of the file, the per-corner UVs and the texture
*paths*. :func:`read_obj` returns the file's faces in file coordinates, unchecked; the public
``storage.mesh_io.read_mesh`` validates them and moves them to world metres. UVs follow the OBJ
convention (origin bottom-left, v up).
"""

from __future__ import annotations

import itertools
import re
import shutil
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import InputError
from .mesh_data import MeshData

_MAP_OPTION_ARGS = {"-blendu": 1, "-blendv": 1, "-cc": 1, "-clamp": 1, "-texres": 1, "-bm": 1, "-boost": 1,
                    "-imfchan": 1, "-mm": 2, "-o": 3, "-s": 3, "-t": 3}  # fmt: skip


def _map_file_name(args: str) -> str:
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
class _Material:
    texture: Path | None
    kd: tuple[float, float, float] | None


def _read_mtl(obj: Path, mtl: Path) -> dict[str, _Material]:
    materials, name, tex, kd = {}, None, None, None
    for line in mtl.read_text(errors="replace").replace("\t", " ").splitlines():
        key, _, rest = line.strip().partition(" ")
        if key == "newmtl":
            if name is not None:
                materials[name] = _Material(tex, kd)
            name, tex, kd = rest.strip(), None, None
        elif key == "map_Kd" and rest.strip():
            tex = (mtl.parent / _map_file_name(rest)).resolve()
        elif key == "Kd":
            kd = tuple(float(x) for x in rest.split()[:3])
    if name is not None:
        materials[name] = _Material(tex, kd)
    return materials


def _numbers(rows: list[str], dtype=np.float64) -> np.ndarray | None:
    """All whitespace-separated numbers of ``rows``, flat, parsed in C; None if any token is not one."""
    try:
        return np.fromstring(" ".join(rows), sep=" ", dtype=dtype)
    except ValueError:
        return None


def _table(path: Path, rows: list[str], widths: tuple[int, ...], what: str) -> np.ndarray:
    """(len(rows), w) float64 for the first width w that fits every row; else the first ``widths[-1]``
    columns of each row (rows shorter than that are an error)."""
    nums = _numbers(rows)
    for width in widths:
        if nums is not None and nums.size == width * len(rows):
            return nums.reshape(len(rows), width)
    keep = min(widths)
    try:
        return np.array([r.split()[:keep] for r in rows], dtype=np.float64).reshape(len(rows), keep)
    except ValueError as err:
        raise InputError(path, f"malformed {what} statement ({err})") from err


def _face_corners(path: Path, rows: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Face statements -> (corner count per face, raw v id per corner, raw vt id per corner or None).

    Ids are as written (1-based, or negative = relative); a corner without a vt gets vt 0. Files of
    triangles in one layout ('v', 'v/vt', 'v//vn', 'v/vt/vn') are parsed in C; others token by token.
    """
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), None
    if rows[0] != rows[0].strip() or rows[-1] != rows[-1].strip():
        rows = [r.strip() for r in rows]
    token = rows[0].split()[0]
    slashes = token.count("/")
    has_vt = slashes >= 1 and token.split("/")[1] != ""
    per_corner = 1 + slashes - (1 if slashes == 2 and not has_vt else 0)
    joined = " ".join(rows)
    n = len(rows)
    if joined.count(" ") == 3 * n - 1 and joined.count("/") == 3 * n * slashes:
        nums = _numbers([joined.replace("/", " ")], np.int64)
        if nums is not None and nums.size == 3 * n * per_corner:
            ids = nums.reshape(3 * n, per_corner)
            return np.full(n, 3, np.int64), ids[:, 0], (ids[:, 1] if has_vt else None)
    split = [r.split() for r in rows]
    counts = np.array([len(r) for r in split], dtype=np.int64)
    parts = [t.split("/") for t in itertools.chain.from_iterable(split)]
    try:
        v = np.array([p[0] for p in parts], dtype=np.int64)
        vt = np.array([int(p[1]) if len(p) > 1 and p[1] else 0 for p in parts], dtype=np.int64)
    except ValueError as err:
        raise InputError(path, f"malformed face statement ({err})") from err
    return counts, v, (vt if vt.any() else None)


def _resolve_ids(raw: np.ndarray, seen: np.ndarray | None) -> np.ndarray:
    """OBJ ids (1-based, or negative = relative to the ``seen`` elements so far) -> 0-based; 0 -> -1."""
    relative = raw + seen if seen is not None else np.full_like(raw, -1)
    return np.where(raw > 0, raw - 1, np.where(raw < 0, relative, -1))


def _seen_before_faces(lines: list[str], key: str) -> np.ndarray:
    """For each face statement, how many ``key`` statements precede it (for negative OBJ ids)."""
    seen, n = [], 0
    for ln in lines:
        k = ln.partition(" ")[0]
        if k == key:
            n += 1
        elif k == "f":
            seen.append(n)
    return np.array(seen, dtype=np.int64)


@dataclass
class _Statements:
    """The parsed statements of an OBJ: xyzc (n, 3|4|6) float64 vertex rows, vt (k, 2|3) float64, counts
    (f,) corners per face, raw_v / raw_vt (sum(counts),) ids as written (raw_vt None without uvs),
    usemtl names with the number of faces before each, mtllib arguments, and the text lines (kept
    only when an id is negative, for relative ids)."""

    xyzc: np.ndarray
    vt: np.ndarray
    counts: np.ndarray
    raw_v: np.ndarray
    raw_vt: np.ndarray | None
    usemtl_names: list[str]
    faces_before_usemtl: list[int]
    mtllibs: list[str]
    lines: list[str] | None = None


_V, _VT, _F, _VN, _OTHER = 1, 2, 3, 4, 0


def _line_kinds(buf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Start offset of every line of ``buf`` ((n,) int64) and its statement kind ((n,) int8)."""
    nl = np.flatnonzero(buf == 10)
    starts = np.concatenate(([0], nl + 1))
    if starts[-1] >= len(buf):
        starts = starts[:-1]
    c0 = buf[starts]
    c1 = buf[np.minimum(starts + 1, len(buf) - 1)]
    c2 = buf[np.minimum(starts + 2, len(buf) - 1)]
    kind = np.zeros(len(starts), np.int8)
    kind[(c0 == ord("v")) & ((c1 == 32) | (c1 == 9))] = _V
    kind[(c0 == ord("v")) & (c1 == ord("t")) & ((c2 == 32) | (c2 == 9))] = _VT
    kind[(c0 == ord("v")) & (c1 == ord("n")) & ((c2 == 32) | (c2 == 9))] = _VN
    kind[(c0 == ord("f")) & ((c1 == 32) | (c1 == 9))] = _F
    return starts, kind


def _csv_block(block: bytes, columns: list[int], dtype) -> np.ndarray | None:
    """Columns of a block of space-separated statements, parsed by pandas' C reader (~6x numpy's
    fromstring); None when the block is not a clean table (the caller then parses line by line)."""
    import io

    import pandas as pd

    try:
        df = pd.read_csv(io.BytesIO(block), sep=" ", header=None, usecols=columns, engine="c",
                         skipinitialspace=True, dtype=np.float64)
    except (ValueError, pd.errors.ParserError):
        return None
    out = df.to_numpy(np.float64)
    if out.shape[1] != len(columns) or (dtype != np.float64 and not np.isfinite(out).all()):
        return None  # integer columns with gaps (a 'v//vn' layout, ragged rows)
    return out if dtype == np.float64 else out.astype(dtype)


def _fast_statements(data: bytes) -> _Statements | None:
    """Parse an OBJ written in blocks (all ``v``, all ``vt``, runs of triangle ``f`` statements, as
    photogrammetry tools write them) without a Python loop per line; None for anything else (polygons,
    negative ids, ragged rows), which the line-by-line parser handles."""
    buf = np.frombuffer(data, np.uint8)
    if len(buf) == 0:
        return None
    starts, kind = _line_kinds(buf)
    ends = np.append(starts[1:], len(buf))
    cut = np.flatnonzero(np.diff(kind)) + 1
    run_lo, run_hi = np.concatenate(([0], cut)), np.concatenate((cut, [len(kind)]))
    parts: dict[int, list[np.ndarray]] = {_V: [], _VT: [], _F: []}
    usemtl, before, mtllibs, n_faces = [], [], [], 0
    for lo, hi in zip(run_lo, run_hi):  # one iteration per run of like statements (a handful)
        k = int(kind[lo])
        block = data[starts[lo]:ends[hi - 1]]
        if k == _OTHER:
            for line in block.decode(errors="replace").replace("\t", " ").splitlines():
                key, _, rest = line.strip().partition(" ")
                if key == "usemtl":
                    usemtl.append(rest.strip())
                    before.append(n_faces)
                elif key == "mtllib":
                    mtllibs.append(rest.strip())
            continue
        if k == _VN:
            continue
        first = data[starts[lo]:ends[lo]].split()
        if k == _F:
            if len(first) != 4 or b"-" in block:
                return None  # polygons or relative ids
            per = first[1].count(b"/") + 1
            if per == 3 and b"//" in first[1]:
                return None
            block = block.replace(b"/", b" ")
            cols = list(range(1, 1 + 3 * per))
            got = _csv_block(block, cols, np.int64)
            if got is None or len(got) != hi - lo:
                return None
            parts[_F].append(got.reshape(-1, per))
            n_faces += hi - lo
        else:
            width = len(first) - 1
            got = _csv_block(block, list(range(1, 1 + width)), np.float64)
            if got is None or len(got) != hi - lo:
                return None
            parts[k].append(got)
    widths = {p.shape[1] for p in parts[_F]}
    if len(widths) > 1 or any(len({p.shape[1] for p in parts[k]}) > 1 for k in (_V, _VT)):
        return None
    xyzc = np.concatenate(parts[_V]) if parts[_V] else np.zeros((0, 3))
    vt = np.concatenate(parts[_VT]) if parts[_VT] else np.zeros((0, 2))
    ids = np.concatenate(parts[_F]) if parts[_F] else np.zeros((0, 1), np.int64)
    return _Statements(xyzc, vt, np.full(n_faces, 3, np.int64), ids[:, 0].copy(),
                       ids[:, 1].copy() if ids.shape[1] >= 2 else None, usemtl, before, mtllibs)


def _slow_statements(path: Path, text: str) -> _Statements:
    """Line by line (any valid OBJ): one pass to bucket the statements, each bucket parsed in bulk."""
    lines = text.replace("\t", " ").splitlines()
    rows: dict[str, list[str]] = {"v": [], "vt": [], "f": [], "mtllib": []}
    usemtl_names, faces_before_usemtl = [], []
    for ln in lines:
        key, _, rest = ln.partition(" ")
        bucket = rows.get(key)
        if bucket is not None:
            bucket.append(rest)
        elif key == "usemtl":
            usemtl_names.append(rest.strip())
            faces_before_usemtl.append(len(rows["f"]))
    xyzc = _table(path, rows["v"], (3, 6, 4), "vertex")
    vt = _table(path, rows["vt"], (2, 3), "texture coordinate")
    counts, raw_v, raw_vt = _face_corners(path, rows["f"])
    return _Statements(xyzc, vt, counts, raw_v, raw_vt, usemtl_names, faces_before_usemtl,
                       [r.strip() for r in rows["mtllib"]], lines)


def read_obj(path: Path) -> MeshData:
    """Faces (polygons fan-triangulated), per-corner UVs, vertex colours and MTL materials of an OBJ,
    in file order and file coordinates. Missing MTL or texture images raise InputError.

    Photogrammetry OBJs (blocks of v, vt and triangle f statements) are parsed block by block with a C
    CSV reader: 387 MB (2.9 M faces) in ~6 s against ~40 s line by line; any other OBJ line by line."""
    data = path.read_bytes()
    st = _fast_statements(data)
    if st is None:
        st = _slow_statements(path, data.decode(errors="replace"))
    xyzc, vt, counts, raw_v, raw_vt = st.xyzc, st.vt, st.counts, st.raw_v, st.raw_vt
    usemtl_names, faces_before_usemtl = st.usemtl_names, st.faces_before_usemtl
    if xyzc.shape[1] not in (3, 4, 6):
        raise InputError(path, f"malformed vertex statements ({xyzc.shape[1]} numbers each)")
    if vt.shape[1] > 2:
        vt = vt[:, :2]
    if (counts < 3).any():
        raise InputError(path, f"{int((counts < 3).sum())} face statements have fewer than 3 vertices")
    negative = (raw_v < 0).any() or (raw_vt is not None and (raw_vt < 0).any())

    def seen(key: str) -> np.ndarray | None:
        return np.repeat(_seen_before_faces(st.lines, key), counts) if negative else None

    v_idx = _resolve_ids(raw_v, seen("v"))
    # fan-triangulate polygons: corners (s, s+j, s+j+1) for j = 1 .. c-2
    ntri = counts - 2
    tri_face = np.repeat(np.arange(len(counts)), ntri)
    j = np.arange(len(tri_face)) - np.repeat(np.cumsum(ntri) - ntri, ntri) + 1
    first = (np.cumsum(counts) - counts)[tri_face]
    corner = np.stack([first, first + j, first + j + 1], axis=1)
    mesh = MeshData(vertices=xyzc[:, :3], faces=v_idx[corner] if len(corner) else np.zeros((0, 3), np.int64))
    if xyzc.shape[1] == 6:
        rgb = xyzc[:, 3:6]
        rgb = rgb * 255.0 if rgb.max() <= 1.0 else rgb  # 0..1 floats by convention, else 0..255
        mesh.vertex_colors = np.clip(np.round(rgb), 0, 255).astype(np.uint8)
    if raw_vt is not None:
        vt_idx = _resolve_ids(raw_vt, seen("vt"))[corner]
        if (vt_idx >= len(vt)).any() or ((vt_idx < 0) & (raw_vt[corner] != 0)).any():
            raise InputError(path, f"texture coordinate ids out of range (file has {len(vt):,} vt)")
        valid = vt_idx >= 0  # corners without a vt get (0, 0)
        mesh.uv = np.zeros((*vt_idx.shape, 2), np.float32)
        mesh.uv[valid] = vt[vt_idx[valid]]
    material_ids: dict[str, int] = {}
    tri_mat = np.full(len(tri_face), -1, np.int64)
    if usemtl_names:
        ids = np.array([material_ids.setdefault(name, len(material_ids)) for name in usemtl_names] + [-1])
        run = np.searchsorted(faces_before_usemtl, np.arange(len(counts)), side="right") - 1
        tri_mat = ids[run][tri_face]  # run -1 (before any usemtl) picks the trailing -1
    _apply_materials(path, mesh, st.mtllibs, material_ids, tri_mat)
    return mesh


def _apply_materials(path: Path, mesh: MeshData, mtllibs: list[str], material_ids: dict, tri_mat: np.ndarray):
    """Per-face texture index and (for untextured materials) face colours from the MTL libraries."""
    materials: dict[str, _Material] = {}
    for lib in mtllibs:
        candidates = [lib] if (path.parent / lib).exists() else lib.split()
        for name in candidates:
            mtl = path.parent / name
            if not mtl.is_file():
                raise InputError(path, f"material library {mtl} (mtllib) not found")
            materials.update(_read_mtl(path, mtl))
    if not material_ids:
        return
    textures: dict[Path, int] = {}
    tex_of_material = np.full(len(material_ids) + 1, -1, np.int16)  # last slot: faces before any usemtl
    kd_of_material = np.full((len(material_ids) + 1, 3), 255, np.uint8)
    needs_colour = False
    mtl_order = {name: i for i, name in enumerate(materials)}
    # textures are numbered in MTL definition order, so write_obj's tex<k> read back as k
    for name in sorted(material_ids, key=lambda n: mtl_order.get(n, len(mtl_order))):
        mid = material_ids[name]
        mat = materials.get(name, _Material(None, None))
        if mat.texture is not None:
            if not mat.texture.is_file():
                raise InputError(path, f"texture image {mat.texture} (map_Kd of material {name!r}) not found")
            tex_of_material[mid] = textures.setdefault(mat.texture, len(textures))
        else:
            needs_colour |= bool((tri_mat == mid).any())
        if mat.kd is not None:
            kd_of_material[mid] = np.clip(np.round(np.array(mat.kd) * 255), 0, 255)
    mesh.textures = [str(t) for t in textures]
    if textures:
        mesh.face_texture = tex_of_material[tri_mat]
    if needs_colour:
        mesh.face_colors = kd_of_material[tri_mat]


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
