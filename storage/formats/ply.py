"""PLY: point clouds by an own parser (exact dtypes, memory-mapped binary, streamed in chunks), meshes
through trimesh (``process=False``), and a binary PLY writer with float64 vertices.

Registered by extension in :mod:`storage.formats.points` (``iter_ply_points``) and
:mod:`storage.formats.meshes` (``read_ply_mesh``).
"""

from __future__ import annotations

import itertools
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path
from storage.errors import InputError
from storage.formats.mesh_data import MeshData
from storage.formats.point_chunk import PointChunk, check_cloud_file, check_finite_points, rgb_to_uint16

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
    "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_ALIASES = {
    "rgb": [("red", "green", "blue"), ("r", "g", "b"), ("diffuse_red", "diffuse_green", "diffuse_blue")],
    "intensity": ["intensity", "Intensity", "scalar_intensity", "scalar_Intensity"],
    "gps_time": ["gps_time", "GpsTime", "scalar_gps_time", "scalar_GpsTime", "time", "timestamp"],
    "classification": ["classification", "Classification", "scalar_classification", "scalar_Classification"],
}


@dataclass(frozen=True)
class _PlyVertexLayout:
    encoding: str  # ascii | binary_little_endian | binary_big_endian
    count: int
    dtype: np.dtype  # one vertex record
    data_start: int  # byte offset of the first vertex (binary) or line index after the header (ascii)


def _ply_vertex_layout(path: Path) -> _PlyVertexLayout:
    elements: list[tuple[str, int, list]] = []
    encoding = None
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise InputError(path, "not a PLY file (first line is not 'ply')")
        header_lines = 1
        while True:
            line = f.readline()
            header_lines += 1
            if not line:
                raise InputError(path, "PLY header has no end_header line (truncated?)")
            words = line.decode("ascii", "replace").split()
            if not words:
                continue
            if words[0] == "format":
                encoding = words[1]
            elif words[0] == "element":
                elements.append((words[1], int(words[2]), []))
            elif words[0] == "property" and elements:
                props = elements[-1][2]
                if words[1] == "list":
                    props.append((words[4], None))
                elif words[1] in _PLY_TYPES:
                    props.append((words[2], _PLY_TYPES[words[1]]))
                else:
                    raise InputError(path, f"unknown PLY property type {words[1]!r}")
            elif words[0] == "end_header":
                break
        header_len = f.tell()
    if encoding not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(path, f"unsupported PLY format {encoding!r}")
    endian = ">" if encoding == "binary_big_endian" else "<"
    skip_bytes, skip_lines = 0, 0
    for name, count, props in elements:
        if any(t is None for _, t in props):
            if name == "vertex":
                raise InputError(path, "PLY vertex element has list properties; not a point cloud")
            raise InputError(path, f"PLY element {name!r} before 'vertex' has list properties; unsupported")
        dtype = np.dtype([(p, endian + t) for p, t in props])
        if name == "vertex":
            start = header_len + skip_bytes if encoding != "ascii" else header_lines + skip_lines
            return _PlyVertexLayout(encoding, count, dtype, start)
        skip_bytes += count * dtype.itemsize
        skip_lines += count
    raise InputError(path, "PLY file has no 'vertex' element")


def _chunk_from_fields(path: Path, rec: np.ndarray) -> PointChunk:
    """Structured records (PLY vertex properties) -> PointChunk, by the usual property names."""
    names = set(rec.dtype.names)
    if not {"x", "y", "z"} <= names:
        raise InputError(path, f"no x/y/z properties (found {sorted(names)})")
    used = {"x", "y", "z"}
    chunk = PointChunk(xyz=np.stack([rec["x"], rec["y"], rec["z"]], axis=1).astype(np.float64))
    for trio in _ALIASES["rgb"]:
        if set(trio) <= names:
            rgb = np.stack([rec[c] for c in trio], axis=1)
            chunk.rgb = rgb_to_uint16(rgb, eight_bit=rgb.dtype == np.uint8)
            used |= set(trio)
            break
    for key in ("intensity", "gps_time", "classification"):
        name = next((a for a in _ALIASES[key] if a in names), None)
        if name is None:
            continue
        col = rec[name]
        if key == "intensity" and col.dtype.kind == "f":
            continue  # float reflectance has no uint16 meaning: left in extra under its own name
        target = {"intensity": np.uint16, "gps_time": np.float64, "classification": np.uint8}[key]
        setattr(chunk, key, col.astype(target))
        used.add(name)
    chunk.extra = {n: np.array(rec[n]) for n in rec.dtype.names if n not in used}
    return chunk


def iter_ply_points(path: Path, chunk_points: int) -> Iterator[PointChunk]:
    check_cloud_file(path)
    lay = _ply_vertex_layout(path)
    if lay.count == 0:
        raise InputError(path, "no points (PLY vertex count is 0)")
    if lay.encoding == "ascii":
        with open(path, "r", errors="replace") as f:
            lines = list(itertools.islice(f, lay.data_start, lay.data_start + lay.count))
        if len(lines) < lay.count:
            raise InputError(path, f"truncated after {len(lines):,} of {lay.count:,} points")
        try:
            table = np.loadtxt(lines, ndmin=2, usecols=range(len(lay.dtype.names)))
        except ValueError as err:
            raise InputError(path, f"malformed ASCII PLY vertex line ({err})") from err
        rec = np.empty(lay.count, dtype=lay.dtype)
        for i, name in enumerate(lay.dtype.names):
            rec[name] = table[:, i]
    else:
        available = (path.stat().st_size - lay.data_start) // lay.dtype.itemsize
        if available < lay.count:
            raise InputError(path, f"truncated after {max(available, 0):,} of {lay.count:,} points")
        rec = np.memmap(path, dtype=lay.dtype, mode="r", offset=lay.data_start, shape=(lay.count,))
    for lo in range(0, lay.count, chunk_points):  # a NaN anywhere fails the file before any chunk
        part = rec[lo : lo + chunk_points]
        check_finite_points(path, np.stack([part["x"], part["y"], part["z"]], axis=1))
    for lo in range(0, lay.count, chunk_points):
        yield _chunk_from_fields(path, np.asarray(rec[lo : lo + chunk_points]))


def read_ply_mesh(path: Path) -> MeshData:
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


__all__ = ["iter_ply_points", "read_ply_mesh", "write_ply"]
