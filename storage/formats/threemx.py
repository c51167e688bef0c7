"""ContextCapture 3MX / 3MXB productions (Bentley's published "3MX specification", version 1) and the OpenCTM
geometry they embed.

A 3MX production is a JSON scene file and a tree of binary nodes::

    Production.3mx                  {"3mxVersion": 1, "layers": [{"type": "meshPyramid", "SRS": "EPSG:32650",
                                      "SRSOrigin": [x, y, z], "root": "Data/Root.3mxb"}, ...]}
    Data/Root.3mxb, Data/Tile_*/…   binary nodes

A ``.3mxb`` file is ``"3MXBO"``, a little-endian uint32 header size, a JSON header ``{"version": 1, "nodes":
[...], "resources": [...]}`` and then the resources' bytes in header order. A node names its resources (a
``geometryBuffer`` in OpenCTM with a ``texture`` id, a ``textureBuffer`` JPEG or PNG, or the same as files
beside the node) and its ``children``: files of finer nodes that replace it. ms3d reads the **finest level**:
the nodes without children, down from each root. Their vertices are metres from the layer's ``SRSOrigin``
in its ``SRS``; a tree without a scene file (a bare ``.3mxb`` root) is in a local frame.

OpenCTM (``OCTM`` version 5): methods RAW (plain arrays) and MG1 (LZMA-packed byte planes, delta-coded
indices) are read; MG2 (fixed-point vertices) is refused with one line. UVs follow the OBJ convention.

>>> idx = restore_mg1_indices(np.array([[0, 1, 2], [0, 1, 2], [1, 0, 3]]))
>>> idx.tolist()
[[0, 1, 2], [0, 2, 2], [1, 1, 4]]
"""

from __future__ import annotations

import io
import json
import lzma
import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.mesh_data import MeshData

MAGIC_3MXB = b"3MXBO"
MAGIC_CTM = b"OCTM"
CTM_HAS_NORMALS = 1


@dataclass(frozen=True)
class ThreeMxLayer:
    """One mesh layer of a scene: root: the absolute path of its root ``.3mxb``; srs: as written ("" when
    none); origin: SRSOrigin (float64 metres, (0, 0, 0) when none)."""

    root: str
    srs: str
    origin: tuple[float, float, float]


# --------------------------------------------------------------------------------------------- OpenCTM


class _Reader:
    """Sequential little-endian reads of a buffer, every overrun an InputError naming ``where``."""

    def __init__(self, buf: bytes, where: str, path):
        self.buf, self.pos, self.where, self.path = buf, 0, where, path

    def take(self, n: int) -> bytes:
        if n < 0 or self.pos + n > len(self.buf):
            raise InputError(self.path, f"{self.where}: truncated (needs {n:,} bytes at {self.pos:,} of "
                                        f"{len(self.buf):,})")
        out = self.buf[self.pos:self.pos + n]
        self.pos += n
        return out

    def i32(self) -> int:
        return struct.unpack("<i", self.take(4))[0]

    def string(self) -> str:
        return self.take(self.i32()).decode("latin-1")

    def tag(self, want: bytes) -> None:
        got = self.take(4)
        if got != want:
            raise InputError(self.path, f"{self.where}: expected the {want.decode()} block, found {got!r}")

    def array(self, dtype: str, count: int) -> np.ndarray:
        return np.frombuffer(self.take(np.dtype(dtype).itemsize * count), dtype).copy()

    def lzma_packed(self, n_bytes: int) -> bytes:
        """An OpenCTM packed block: int32 packed size, 5 LZMA property bytes, the LZMA stream; ``n_bytes``
        unpacked."""
        packed = self.i32()
        props = self.take(5)
        data = self.take(packed)
        try:
            out = lzma.LZMADecompressor(format=lzma.FORMAT_ALONE).decompress(
                props + struct.pack("<Q", n_bytes) + data, max_length=n_bytes)
        except lzma.LZMAError as e:
            raise InputError(self.path, f"{self.where}: corrupt LZMA data ({e})") from None
        if len(out) != n_bytes:
            raise InputError(self.path, f"{self.where}: LZMA data unpacks to {len(out):,} bytes, expected {n_bytes:,}")
        return out


def _byte_planes(raw: bytes, count: int, size: int) -> np.ndarray:
    """(count, size) uint32 of MG1's interleaved 32-bit words: byte planes most significant first, each
    plane component-major (component k of element i at ``k * count + i``)."""
    a = np.frombuffer(raw, np.uint8).reshape(4, size, count).astype(np.uint32)
    return ((a[0] << 24) | (a[1] << 16) | (a[2] << 8) | a[3]).T.copy()


def restore_mg1_indices(d: np.ndarray) -> np.ndarray:
    """(t, 3) int64 triangle indices from MG1's delta code (t, 3): the first index is a running sum; the
    third is relative to the first; the second is relative to the previous triangle's second when both
    share their first index, else to their own first."""
    d = np.asarray(d, np.int64)  # uint32 words: the sums below wrap modulo 2**32, as OpenCTM's unsigned ones
    out = np.empty_like(d)
    if not len(d):
        return out
    first = np.cumsum(d[:, 0])
    out[:, 0] = first
    out[:, 2] = d[:, 2] + first
    new_run = np.ones(len(d), bool)
    new_run[1:] = first[1:] != first[:-1]
    starts = np.flatnonzero(new_run)
    run_of = np.cumsum(new_run) - 1
    cs = np.cumsum(d[:, 1])
    before = np.where(starts > 0, cs[starts - 1], 0)  # the sum before each run
    out[:, 1] = cs - before[run_of] + first[starts][run_of]
    return out % (1 << 32)


def read_ctm(buf: bytes, path=None, where: str = "OpenCTM") -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """(vertices (n, 3) float64, faces (t, 3) int64, per-vertex uv (n, 2) float32 or None) of an OpenCTM
    buffer. InputError (naming ``path`` and ``where``) when it is not OpenCTM, truncated, corrupt, or MG2."""
    r = _Reader(buf, where, path)
    if r.take(4) != MAGIC_CTM:
        raise InputError(path, f"{where}: not OpenCTM geometry (no OCTM signature)")
    version = r.i32()
    method = r.take(4).rstrip(b"\0")
    nv, nt, n_uv, n_attr, flags = (r.i32() for _ in range(5))
    if version != 5:
        raise InputError(path, f"{where}: OpenCTM version {version} (only version 5 is read)")
    if min(nv, nt, n_uv, n_attr) < 0 or nv == 0 or nt == 0:
        raise InputError(path, f"{where}: OpenCTM counts are invalid ({nv} vertices, {nt} triangles)")
    r.string()  # comment
    uv = None
    if method == b"RAW":
        r.tag(b"INDX")
        faces = r.array("<u4", 3 * nt).reshape(-1, 3).astype(np.int64)
        r.tag(b"VERT")
        vertices = r.array("<f4", 3 * nv).reshape(-1, 3)
        if flags & CTM_HAS_NORMALS:
            r.tag(b"NORM")
            r.take(12 * nv)
        for k in range(n_uv):
            r.tag(b"TEXC")
            r.string(), r.string()
            tex = r.array("<f4", 2 * nv).reshape(-1, 2)
            uv = tex if k == 0 else uv
    elif method == b"MG1":
        r.tag(b"INDX")
        faces = restore_mg1_indices(_byte_planes(r.lzma_packed(12 * nt), nt, 3))
        r.tag(b"VERT")
        vertices = _byte_planes(r.lzma_packed(12 * nv), 3 * nv, 1).view(np.float32).reshape(-1, 3)
        if flags & CTM_HAS_NORMALS:
            r.tag(b"NORM")
            r.lzma_packed(12 * nv)
        for k in range(n_uv):
            r.tag(b"TEXC")
            r.string(), r.string()
            tex = _byte_planes(r.lzma_packed(8 * nv), 2 * nv, 1).view(np.float32).reshape(-1, 2)
            uv = tex if k == 0 else uv
    else:
        raise InputError(path, f"{where}: OpenCTM method {method.decode('latin-1')!r} is not read (RAW and MG1 "
                               "are); re-export the production with another geometry compression")
    if faces.size and (faces.min() < 0 or faces.max() >= nv):
        raise InputError(path, f"{where}: triangle indices out of range (0..{nv - 1})")
    return vertices.astype(np.float64), faces, None if uv is None else uv.astype(np.float32)


# ------------------------------------------------------------------------------------------------ 3MXB


def read_3mxb(path: str | Path) -> tuple[dict, dict[str, bytes]]:
    """(header, {resource id: bytes}) of a ``.3mxb`` node file. InputError naming it when it is not 3MXB,
    has a broken header, or is shorter than its resources."""
    path = Path(path)
    try:
        buf = path.read_bytes()
    except FileNotFoundError:
        raise InputError(path, "3MXB node file not found (named as a child by its parent node)") from None
    if not buf.startswith(MAGIC_3MXB) or len(buf) < 9:
        raise InputError(path, "not a 3MXB file (no 3MXBO signature)")
    n = struct.unpack_from("<I", buf, 5)[0]
    try:
        header = json.loads(buf[9:9 + n].decode("utf-8"))
        resources = header["resources"]
        header["nodes"]
    except (ValueError, KeyError, TypeError, UnicodeDecodeError) as e:
        raise InputError(path, f"the 3MXB header is not valid JSON with nodes and resources ({e})") from None
    blobs, off = {}, 9 + n
    for res in resources:
        size = int(res.get("size", 0)) if res.get("type", "").endswith("Buffer") else 0
        if off + size > len(buf):
            raise InputError(path, f"truncated: resource {res.get('id')!r} needs {size:,} bytes at {off:,}, the file "
                                   f"has {len(buf):,}")
        blobs[str(res.get("id"))] = buf[off:off + size]
        off += size
    return header, blobs


def _decode_image(data: bytes, path, rid: str) -> np.ndarray | None:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            return np.asarray(im.convert("RGB"))
    except Exception:  # noqa: BLE001 - a bad texture leaves its faces untextured, with a warning
        return None


def _node_mesh(path: Path, header: dict, blobs: dict[str, bytes], node: dict, textures: dict,
               warnings: list[str]) -> Iterator[MeshData]:
    """The geometry resources of one leaf node as MeshData (file coordinates)."""
    res_by_id = {str(r.get("id")): r for r in header["resources"]}
    for rid in node.get("resources", []):
        res = res_by_id.get(str(rid))
        if res is None:
            raise InputError(path, f"node {node.get('id')!r} names resource {rid!r}, which the header does not list")
        kind = res.get("type")
        if kind not in ("geometryBuffer", "geometryFile"):
            continue
        if res.get("format", "ctm") != "ctm":
            raise InputError(path, f"geometry resource {rid!r} has format {res.get('format')!r} (only OpenCTM is read)")
        if kind == "geometryFile":
            src = path.parent / str(res.get("file", ""))
            try:
                data = src.read_bytes()
            except OSError:
                raise InputError(src, "3MX geometry file not found (named by a node)") from None
        else:
            data = blobs[str(rid)]
        v, f, uv = read_ctm(data, path, f"geometry {rid!r}")
        tex_id = res.get("texture")
        ref, face_tex = None, np.full(len(f), -1, np.int16)
        if tex_id is not None and uv is not None:
            ref = textures.get((str(path), str(tex_id)))
            if ref is None:
                img, tres = None, res_by_id.get(str(tex_id))
                if tres is not None and tres.get("type") == "textureBuffer":
                    img = _decode_image(blobs[str(tex_id)], path, str(tex_id))
                elif tres is not None and tres.get("type") == "textureFile":
                    tfile = path.parent / str(tres.get("file", ""))
                    img = _decode_image(tfile.read_bytes(), path, str(tex_id)) if tfile.exists() else None
                if img is None:
                    warnings.append(f"{path}: texture {tex_id!r} is missing or unreadable; its faces load untextured")
                    ref = ""
                else:
                    ref = f"{path}#{tex_id}"
                    textures[ref] = img
                textures[(str(path), str(tex_id))] = ref
        mesh = MeshData(vertices=v, faces=f, warnings=[])
        if uv is not None:
            mesh.uv = uv[f]
            if ref:
                face_tex[:] = 0
                mesh.textures = [ref]
                mesh.embedded_textures = {ref: textures[ref]}
            mesh.face_texture = face_tex
        yield mesh


def iter_leaf_meshes(root: str | Path) -> Iterator[MeshData]:
    """The finest-level geometry of the node tree under ``root`` (a ``.3mxb``), one MeshData per geometry
    resource, in file coordinates, depth first in child order. A node file reached twice is read once."""
    root = Path(root).absolute()
    stack, seen, textures = [root], set(), {}
    while stack:
        path = stack.pop()
        if path in seen:
            continue
        seen.add(path)
        header, blobs = read_3mxb(path)
        warnings: list[str] = []
        children = []
        for node in header["nodes"]:
            kids = node.get("children") or []
            if kids:
                children.extend(path.parent / str(c) for c in kids)
                continue
            for mesh in _node_mesh(path, header, blobs, node, textures, warnings):
                mesh.warnings = warnings
                warnings = []
                yield mesh
        stack.extend(reversed(children))


def read_scene(path: str | Path) -> list[ThreeMxLayer]:
    """The mesh layers of a ``.3mx`` scene file. InputError naming it when it is not a 3MX scene or has no
    mesh layer."""
    path = Path(path).absolute()
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(path, "3MX scene file not found") from None
    except (ValueError, UnicodeDecodeError) as e:
        raise InputError(path, f"not a 3MX scene (not JSON: {e})") from None
    if not isinstance(doc, dict) or "layers" not in doc:
        raise InputError(path, "not a 3MX scene (no 'layers')")
    layers = []
    for layer in doc["layers"]:
        if not isinstance(layer, dict) or layer.get("type") != "meshPyramid" or not layer.get("root"):
            continue
        origin = layer.get("SRSOrigin") or [0.0, 0.0, 0.0]
        try:
            o = tuple(float(x) for x in origin)
            assert len(o) == 3
        except (TypeError, ValueError, AssertionError):
            raise InputError(path, f"layer {layer.get('id')!r}: SRSOrigin {origin!r} is not three numbers") from None
        layers.append(ThreeMxLayer(str(path.parent / layer["root"]), str(layer.get("SRS", "")), o))
    if not layers:
        raise InputError(path, "3MX scene without a meshPyramid layer")
    return layers


def read_3mx(path: str | Path) -> MeshData:
    """A ``.3mx`` scene (every mesh layer) or a bare ``.3mxb`` root: the finest level as one MeshData, in the
    coordinates of the scene's first layer (its SRSOrigin is the production's offset,
    :func:`storage.formats.production.scene_production`; a further layer is moved by the difference of its
    SRSOrigin). Texture images are decoded into ``embedded_textures``."""
    path = Path(path)
    if path.suffix.lower() == ".3mx":
        parts = []
        layers = read_scene(path)
        for layer in layers:
            shift = np.subtract(layer.origin, layers[0].origin)
            for m in iter_leaf_meshes(layer.root):
                m.vertices = m.vertices + shift
                parts.append(m)
    else:
        parts = list(iter_leaf_meshes(path))
    if not parts:
        raise InputError(path, "no geometry at the finest level of the 3MX node tree")
    return MeshData.concat(parts, source=str(path))


def scene_srs(path: str | Path) -> str | None:
    """The SRS of a ``.3mx`` scene's first mesh layer ("" or None when it names none / for a bare root)."""
    path = Path(path)
    if path.suffix.lower() != ".3mx":
        return None
    return read_scene(path)[0].srs or None


def root_nodes(files: list[Path]) -> list[Path]:
    """Of the ``.3mxb`` files under a folder, the roots: those no other file names as a child (a production
    read from its folder is read from its roots down; its other node files are levels of the same tree)."""
    named = set()
    for f in files:
        try:
            header, _ = read_3mxb(f)
        except InputError:
            continue
        for node in header["nodes"]:
            named.update((f.parent / str(c)).resolve() for c in node.get("children") or [])
    return [f for f in files if f.resolve() not in named]


def select_3mx(paths: list[str]) -> tuple[list[str], list[tuple[str, str]]]:
    """Of a folder scan's files, the 3MX entry points: every ``.3mx`` scene, and the root ``.3mxb`` nodes not
    under a scene's folder; the other ``.3mxb`` files are levels of those trees (returned as skipped, with
    why). Other files pass through. Returns (kept, skipped (path, why))."""
    scenes = [Path(p) for p in paths if Path(p).suffix.lower() == ".3mx"]
    nodes = [Path(p) for p in paths if Path(p).suffix.lower() == ".3mxb"]
    if not nodes:
        return list(paths), []
    under_scene = {n for n in nodes if any(sc.parent in n.parents for sc in scenes)}
    roots = set(root_nodes([n for n in nodes if n not in under_scene]))
    kept = [p for p in paths if Path(p).suffix.lower() != ".3mxb" or Path(p) in roots]
    skipped = [(str(n), "a node of a 3MX production read from its scene file" if n in under_scene else
                "a node of a 3MX tree read from its root node") for n in nodes if n not in roots]
    return kept, sorted(skipped)


__all__ = ["ThreeMxLayer", "iter_leaf_meshes", "read_3mx", "read_3mxb", "read_ctm", "read_scene",
           "restore_mg1_indices", "root_nodes", "scene_srs", "select_3mx"]
