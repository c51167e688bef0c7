"""A glTF 2.0 binary (glb) writer for tile content, with per-face provenance as EXT_mesh_features.

``build_glb(mesh)`` turns a :class:`GltfMesh` (float32 y-up positions, faces, optional uv/textures and
vertex colours, one provenance row per feature) into glb bytes:

- one primitive per texture image (``KHR_materials_unlit``: photogrammetric textures already hold the
  light, so no normals) and one for vertex-coloured faces (lit, with normals): glTF multiplies colour by
  texture, so the two never share a primitive;
- feature ids per vertex (``_FEATURE_ID_0``, ``EXT_mesh_features``) index one
  ``EXT_structural_metadata`` property table (grade, source, region); a vertex used by faces of
  different features is duplicated, so every face reads one feature; a mesh with per-face quality adds a
  second set (``_FEATURE_ID_1``, one feature per face) and table (:mod:`tasks.export.face_quality`);
- normals (lit primitives) are area-weighted per vertex; COLOR_0 is linear RGBA8 (input colours are sRGB);
- ``compression="draco"`` encodes each primitive with ``KHR_draco_mesh_compression`` (DracoPy), positions
  quantized to ``DRACO_POSITION_STEP_M`` (bits chosen from the primitive's extent).

``read_glb`` / ``glb_positions`` read back what is needed by tests and bounding volumes.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from tasks.export.face_quality import (
    FACE_QUALITY_CLASS,
    face_quality_table,
    feature_id_values,
    split_per_face,
)
from tasks.export.vertex_split import split_by_feature
from tasks.geometry.triangles import vertex_normals

GLB_MAGIC, CHUNK_JSON, CHUNK_BIN = 0x46546C67, 0x4E4F534A, 0x004E4942
MAX_GLB_BYTES = 1 << 30  # far below the uint32 length field and what viewers load
FLOAT, UBYTE, USHORT, UINT = 5126, 5121, 5123, 5125
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
DRACO_POSITION_STEP_M = 0.00025  # Draco position quantization step: <= 0.125 mm error

GRADE_NAMES = {0: "good", 1: "bad", -1: "unknown"}
SOURCE_NAMES = {0: "mesh", 1: "rebuilt"}

PROVENANCE_SCHEMA = {
    "id": "ms3d_provenance",
    "name": "ms3d per-face provenance",
    "enums": {
        "grade": {"valueType": "INT8", "values": [{"name": n, "value": v} for v, n in GRADE_NAMES.items()]},
        "source": {"valueType": "INT8", "values": [{"name": n, "value": v} for v, n in SOURCE_NAMES.items()]},
    },
    "classes": {
        "provenance": {
            "name": "Face provenance",
            "properties": {
                "grade": {"type": "ENUM", "enumType": "grade", "required": True,
                          "description": "the grade of the patch the face came from (the grader named in the run report)"},
                "source": {"type": "ENUM", "enumType": "source", "required": True,
                           "description": "mesh: retained original mesh; rebuilt: regenerated from fused points"},
                "region": {"type": "SCALAR", "componentType": "INT32", "required": True,
                           "description": "bad-region number, -1 for none"},
            },
        }
    },
}  # fmt: skip


@dataclass(frozen=True, eq=False)
class GltfImage:
    """An encoded texture image: ``data`` JPEG or PNG bytes, ``mime`` 'image/jpeg' or 'image/png'."""

    data: bytes
    mime: str


@dataclass(frozen=True, eq=False)
class GltfMesh:
    """What one glb holds.

    positions: (n, 3) float32 metres, glTF y-up. faces: (m, 3) int. feature: (m,) int index into the
    provenance rows ``grade`` (k,) int8, ``source`` (k,) int8, ``region`` (k,) int32.
    uv: (n, 2) float32 glTF convention (origin top-left) or None. face_texture: (m,) int16 index into
    ``images``, -1 for a vertex-coloured face. vertex_colors: (n, 3) uint8 sRGB or None (then grey).
    face_deviation, face_confidence: (m,) float32 per-face quality (:mod:`tasks.export.face_quality`) or None.
    """

    positions: np.ndarray
    faces: np.ndarray
    feature: np.ndarray
    grade: np.ndarray
    source: np.ndarray
    region: np.ndarray
    face_texture: np.ndarray
    uv: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
    images: list[GltfImage] = field(default_factory=list)
    face_deviation: np.ndarray | None = None
    face_confidence: np.ndarray | None = None


# The export's vertex normals (:func:`tasks.geometry.triangles.vertex_normals`): faces summed face by face,
# (0, 1, 0) (up) where undefined; written as float32.
EXPORT_NORMALS = {"order": "faces", "eps": 1e-20, "undefined": (0.0, 1.0, 0.0)}


def _srgb_table() -> np.ndarray:
    c = np.arange(256, dtype=np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return np.clip(np.round(lin * 255.0), 0, 255).astype(np.uint8)


_SRGB_TO_LINEAR = _srgb_table()  # (256,) uint8: the IEC 61966-2-1 decoding of every 8-bit value


def srgb_to_linear_u8(rgb: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 sRGB -> (n, 4) uint8 linear RGBA (alpha 255), as glTF's COLOR_0 wants."""
    out = np.full((len(rgb), 4), 255, np.uint8)
    out[:, :3] = _SRGB_TO_LINEAR[np.asarray(rgb, np.uint8)]
    return out


class _Builder:
    """Accumulates buffer views / accessors into one binary chunk."""

    def __init__(self):
        self.chunks: list[bytes] = []
        self.length = 0
        self.doc: dict = {"bufferViews": [], "accessors": []}

    def view(self, data: bytes | np.ndarray, target: int | None = None, stride: int | None = None, align: int = 8) -> int:
        """Append ``data`` (bytes, or a C-contiguous array kept as it is: no copy until the glb is written)."""
        pad = (-self.length) % align
        if pad:
            self.chunks.append(b"\0" * pad)
            self.length += pad
        if isinstance(data, np.ndarray):
            data = np.ascontiguousarray(data).reshape(-1).view(np.uint8)  # bytes-like, len = bytes (also when empty)
        bv = {"buffer": 0, "byteOffset": self.length, "byteLength": len(data)}
        if target is not None:
            bv["target"] = target
        if stride is not None:
            bv["byteStride"] = stride
        self.chunks.append(data)
        self.length += len(data)
        self.doc["bufferViews"].append(bv)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, array: np.ndarray | None, ctype: int, atype: str, count: int, *, target=None, stride=None,
                 normalized=False, minmax=False, view=True) -> int:
        acc = {"componentType": ctype, "count": int(count), "type": atype}
        if view:
            acc["bufferView"] = self.view(np.ascontiguousarray(array), target, stride)
        if normalized:
            acc["normalized"] = True
        if minmax:
            acc["min"] = [float(v) for v in array.min(axis=0)]
            acc["max"] = [float(v) for v in array.max(axis=0)]
        self.doc["accessors"].append(acc)
        return len(self.doc["accessors"]) - 1


_DRACO_TYPES = {"POSITION": 0, "NORMAL": 1, "COLOR_0": 2, "TEXCOORD_0": 3, "_FEATURE_ID_0": 4}


@lru_cache(maxsize=8)
def _draco_unique_ids(has_uv: bool, has_color: bool, has_normals: bool) -> dict[str, int]:
    """Which unique id DracoPy gives each attribute, found by encoding a one-triangle probe."""
    import DracoPy

    p = np.eye(3, dtype=np.float32)
    enc = DracoPy.encode(p, np.array([[0, 1, 2]], np.uint32), normals=p.astype(np.float64) if has_normals else None,
                         tex_coord=np.zeros((3, 2)) if has_uv else None,
                         colors=np.zeros((3, 4), np.uint8) if has_color else None,
                         generic_attributes={20: np.zeros((3, 1), np.uint16)})
    dec = DracoPy.decode(enc)
    by_type = {a["attribute_type"]: a["unique_id"] for a in dec.attributes}
    by_type.setdefault(0, 0)  # positions are not listed among the extra attributes
    return {name: by_type[t] for name, t in _DRACO_TYPES.items() if t in by_type}


def _primitive(b: _Builder, pos, faces, normals, uv, colors, fid, material: int, compression: str,
               fid1=None) -> dict:
    """Append one primitive's data; returns the primitive dict. fid1: (n,) the face-quality feature id of each
    vertex (uncompressed only), or None."""
    n = len(pos)
    idx_type, idx_dtype = (USHORT, np.uint16) if n < 65535 else (UINT, np.uint32)
    fid_u16 = fid.astype(np.uint16)
    if compression == "draco":
        import DracoPy

        ids = _draco_unique_ids(uv is not None, colors is not None, normals is not None)
        extent = float(np.ptp(pos, axis=0).max()) if n else 1.0
        bits = int(np.clip(np.ceil(np.log2(max(extent, 1e-3) / DRACO_POSITION_STEP_M)), 11, 30))
        data = DracoPy.encode(
            pos, faces.astype(np.uint32), quantization_bits=bits, compression_level=5,  # 5: smaller and faster than 7 here
            normals=None if normals is None else normals.astype(np.float64), normal_quantization_bits=10,
            tex_coord=None if uv is None else uv.astype(np.float64), tex_coord_quantization_bits=14,
            colors=colors, generic_attributes={20: fid_u16.reshape(-1, 1)},
        )  # fmt: skip
        attrs = {"POSITION": b.accessor(pos, FLOAT, "VEC3", n, minmax=True, view=False),
                 "_FEATURE_ID_0": b.accessor(None, USHORT, "SCALAR", n, view=False)}
        if normals is not None:
            attrs["NORMAL"] = b.accessor(None, FLOAT, "VEC3", n, view=False)
        if uv is not None:
            attrs["TEXCOORD_0"] = b.accessor(None, FLOAT, "VEC2", n, view=False)
        if colors is not None:
            attrs["COLOR_0"] = b.accessor(None, UBYTE, "VEC4", n, normalized=True, view=False)
        indices = b.accessor(None, idx_type, "SCALAR", faces.size, view=False)
        ext = {"KHR_draco_mesh_compression": {"bufferView": b.view(data), "attributes": {k: ids[k] for k in attrs}}}
    else:
        attrs = {"POSITION": b.accessor(pos, FLOAT, "VEC3", n, target=ARRAY_BUFFER, minmax=True)}
        if normals is not None:
            attrs["NORMAL"] = b.accessor(normals, FLOAT, "VEC3", n, target=ARRAY_BUFFER)
        if uv is not None:
            attrs["TEXCOORD_0"] = b.accessor(uv, FLOAT, "VEC2", n, target=ARRAY_BUFFER)
        if colors is not None:
            attrs["COLOR_0"] = b.accessor(colors, UBYTE, "VEC4", n, target=ARRAY_BUFFER, normalized=True)
        padded = np.zeros((n, 2), np.uint16)  # vertex attribute elements must be 4-byte aligned
        padded[:, 0] = fid_u16
        attrs["_FEATURE_ID_0"] = b.accessor(padded, USHORT, "SCALAR", n, target=ARRAY_BUFFER, stride=4)
        if fid1 is not None:
            values, ctype = feature_id_values(fid1)
            attrs["_FEATURE_ID_1"] = b.accessor(values, ctype, "SCALAR", n, target=ARRAY_BUFFER, stride=4)
        indices = b.accessor(faces.astype(idx_dtype).reshape(-1), idx_type, "SCALAR", faces.size,
                             target=ELEMENT_ARRAY_BUFFER)
        ext = {}
    ext["EXT_mesh_features"] = {"featureIds": [{"featureCount": len(np.unique(fid)),
                                                "attribute": 0, "propertyTable": 0, "label": "provenance"}]}
    if fid1 is not None:
        ext["EXT_mesh_features"]["featureIds"].append({"featureCount": len(faces), "attribute": 1,
                                                       "propertyTable": 1, "label": "face_quality"})
    return {"attributes": attrs, "indices": indices, "material": material, "mode": 4, "extensions": ext}


def build_glb(mesh: GltfMesh, compression: str = "none") -> bytes:
    """glb bytes of ``mesh`` (see the module docstring). compression: "none" or "draco"."""
    return b"".join(glb_parts(mesh, compression))


def glb_parts(mesh: GltfMesh, compression: str = "none") -> list:
    """The glb of ``mesh`` as a list of bytes-like pieces (header, JSON, the binary chunk's views)."""
    if compression not in ("none", "draco"):
        raise ValueError(f"compression must be 'none' or 'draco', not {compression!r}")
    b = _Builder()
    doc = b.doc
    doc.update({"asset": {"version": "2.0", "generator": "ms3d export"}, "scene": 0,
                "scenes": [{"nodes": [0]}], "nodes": [{"mesh": 0, "name": "tile"}], "materials": []})
    used = ["EXT_mesh_features", "EXT_structural_metadata"]
    n_feat = len(mesh.grade)
    if n_feat > 65535:
        raise ValueError(f"{n_feat} provenance rows exceed the 65,535 features of a UNSIGNED_SHORT feature id")
    table = {"class": "provenance", "count": n_feat, "name": "provenance", "properties": {}}
    for name, arr, dtype in (("grade", mesh.grade, np.int8), ("source", mesh.source, np.int8),
                             ("region", mesh.region, np.int32)):
        table["properties"][name] = {"values": b.view(np.asarray(arr, dtype).tobytes(), align=8)}
    schema, tables = PROVENANCE_SCHEMA, [table]
    quality = mesh.face_deviation is not None and mesh.face_confidence is not None and compression == "none"
    if quality:
        schema = {**schema, "classes": {**schema["classes"], "face_quality": FACE_QUALITY_CLASS}}
        tables.append(face_quality_table(lambda data: b.view(data, align=8), mesh.face_deviation, mesh.face_confidence))
    doc["extensions"] = {"EXT_structural_metadata": {"schema": schema, "propertyTables": tables}}

    if mesh.images:
        doc["samplers"] = [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}]
        doc["images"] = [{"bufferView": b.view(im.data), "mimeType": im.mime} for im in mesh.images]
        doc["textures"] = [{"sampler": 0, "source": i} for i in range(len(mesh.images))]
    primitives = []
    groups = np.unique(mesh.face_texture) if len(mesh.faces) else np.zeros(0, np.int16)
    for g in groups.tolist():
        sel = np.flatnonzero(mesh.face_texture == g)
        fid1 = None
        if quality:  # a vertex per face corner (each face its own feature of the face_quality table)
            faces, src, fid1 = split_per_face(mesh.faces[sel], sel)
            fid = np.repeat(np.asarray(mesh.feature[sel], np.int64), 3)
        else:
            faces, src, fid = split_by_feature(mesh.faces[sel], mesh.feature[sel])
        pos = np.ascontiguousarray(mesh.positions[src], np.float32)
        normals = None  # unlit textured primitives need none
        if g >= 0:
            uv = np.ascontiguousarray(mesh.uv[src], np.float32)
            colors = None
            doc["materials"].append({"name": f"texture{g}", "doubleSided": True,
                                     "pbrMetallicRoughness": {"baseColorTexture": {"index": int(g)},
                                                              "metallicFactor": 0.0, "roughnessFactor": 1.0},
                                     "extensions": {"KHR_materials_unlit": {}}})
            if "KHR_materials_unlit" not in used:
                used.append("KHR_materials_unlit")
        else:
            uv = None
            rgb = mesh.vertex_colors[src] if mesh.vertex_colors is not None else np.full((len(src), 3), 180, np.uint8)
            colors = srgb_to_linear_u8(rgb)
            normals = vertex_normals(pos, faces, **EXPORT_NORMALS).astype(np.float32)
            doc["materials"].append({"name": "vertex_colour", "doubleSided": True,
                                     "pbrMetallicRoughness": {"metallicFactor": 0.0, "roughnessFactor": 1.0}})
        primitives.append(_primitive(b, pos, faces, normals, uv, colors, fid, len(doc["materials"]) - 1, compression,
                                     fid1))
    if compression == "draco":
        used.append("KHR_draco_mesh_compression")
        doc["extensionsRequired"] = ["KHR_draco_mesh_compression"]
    doc["meshes"] = [{"primitives": primitives, "name": "tile"}]
    doc["extensionsUsed"] = used
    doc["buffers"] = [{"byteLength": b.length}]
    return _pack_parts(doc, b.chunks, b.length)


def _pack(doc: dict, chunks: list, length: int) -> bytes:
    return b"".join(_pack_parts(doc, chunks, length))


def _pack_parts(doc: dict, chunks: list, length: int) -> list:
    """glb header + JSON chunk, then the binary chunk's pieces as they are (no copy) and its padding."""
    js = json.dumps(doc, separators=(",", ":")).encode()
    js += b" " * ((-len(js)) % 4)
    bin_pad = (-length) % 4
    total = 12 + 8 + len(js) + 8 + length + bin_pad
    if total > MAX_GLB_BYTES:
        raise ValueError(f"glb of {total:,} bytes exceeds {MAX_GLB_BYTES:,}: use smaller tiles")
    head = struct.pack("<III", GLB_MAGIC, 2, total) + struct.pack("<II", len(js), CHUNK_JSON) + js
    return [head + struct.pack("<II", length + bin_pad, CHUNK_BIN), *chunks, b"\0" * bin_pad]


def read_glb(data: bytes) -> tuple[dict, bytes]:
    """(JSON document, binary chunk) of glb bytes."""
    magic, version, total = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2:
        raise ValueError("not a glTF 2.0 binary")
    jlen, _ = struct.unpack_from("<II", data, 12)
    doc = json.loads(data[20 : 20 + jlen])
    off = 20 + jlen
    binary = b""
    if off < total:
        blen, _ = struct.unpack_from("<II", data, off)
        binary = data[off + 8 : off + 8 + blen]
    return doc, binary


def accessor_array(doc: dict, binary: bytes, index: int) -> np.ndarray:
    """An uncompressed accessor as an array ((count,) or (count, k))."""
    acc = doc["accessors"][index]
    bv = doc["bufferViews"][acc["bufferView"]]
    dtype = {FLOAT: np.float32, UBYTE: np.uint8, USHORT: np.uint16, UINT: np.uint32}[acc["componentType"]]
    k = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}[acc["type"]]
    itemsize = np.dtype(dtype).itemsize
    stride = bv.get("byteStride", k * itemsize)
    start = bv["byteOffset"] + acc.get("byteOffset", 0)
    raw = np.frombuffer(binary, np.uint8, count=stride * (acc["count"] - 1) + k * itemsize, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(acc["count"], k * itemsize), strides=(stride, 1))
    out = np.ascontiguousarray(rows).view(dtype).reshape(acc["count"], k)
    return out[:, 0] if k == 1 else out


def glb_primitives(data: bytes) -> list[dict[str, np.ndarray]]:
    """Per primitive: {"POSITION": (n, 3) float32, ..., "indices": (m, 3)}, decoding Draco if used."""
    doc, binary = read_glb(data)
    out = []
    for prim in doc["meshes"][0]["primitives"]:
        draco = prim.get("extensions", {}).get("KHR_draco_mesh_compression")
        if draco:
            import DracoPy

            bv = doc["bufferViews"][draco["bufferView"]]
            dec = DracoPy.decode(binary[bv["byteOffset"] : bv["byteOffset"] + bv["byteLength"]])
            by_id = {a["unique_id"]: a["data"] for a in dec.attributes}
            arrays = {"POSITION": np.asarray(dec.points, np.float32), "indices": np.asarray(dec.faces)}
            for name, uid in draco["attributes"].items():
                if name != "POSITION" and uid in by_id:
                    arrays[name] = np.asarray(by_id[uid])
        else:
            arrays = {name: accessor_array(doc, binary, i) for name, i in prim["attributes"].items()}
            if "indices" in prim:  # POINTS primitives (the MLS overlay) have none
                arrays["indices"] = accessor_array(doc, binary, prim["indices"]).reshape(-1, 3)
        out.append(arrays)
    return out


def glb_positions(data: bytes) -> np.ndarray:
    """All vertex positions of a glb: (n, 3) float32, glTF y-up."""
    prims = glb_primitives(data)
    return np.concatenate([p["POSITION"] for p in prims]) if prims else np.zeros((0, 3), np.float32)
