"""Write a small ContextCapture-style 3MX production (a ``.3mx`` scene and a tree of ``.3mxb`` nodes with
OpenCTM geometry and JPEG textures), for tests of :mod:`storage.formats.threemx`.

The tree: a root node holding a coarse copy of the mesh (every ``coarse_step``-th face) whose children are
``n_split`` x ``n_split`` leaf nodes (faces grouped by centroid in xy), each in its own file under
``Data/Tile_<k>/``. The leaves together hold every face once: the finest level a reader keeps. Geometry is
OpenCTM version 5, ``RAW`` or ``MG1`` (LZMA-packed byte planes, triangles sorted and delta-coded as
OpenCTM's MG1 writer does).
"""

from __future__ import annotations

import io
import json
import lzma
import struct
from pathlib import Path

import numpy as np


def _string(s: str) -> bytes:
    b = s.encode("latin-1")
    return struct.pack("<i", len(b)) + b


def _pack(words: np.ndarray) -> bytes:
    """MG1's packed block of (count, size) uint32 words: byte planes (most significant first), each
    component-major, LZMA-compressed; int32 packed size, 5 property bytes, the stream."""
    w = np.ascontiguousarray(words, np.uint32)
    count, size = w.shape
    planes = np.stack([(w.T >> s) & 0xFF for s in (24, 16, 8, 0)]).astype(np.uint8)  # (4, size, count)
    alone = lzma.compress(planes.tobytes(), format=lzma.FORMAT_ALONE)
    props, stream = alone[:5], alone[13:]
    return struct.pack("<i", len(stream)) + props + stream


def _mg1_deltas(faces: np.ndarray) -> np.ndarray:
    """Triangles rotated (smallest index first) and sorted, as (t, 3) uint32 MG1 deltas."""
    f = np.asarray(faces, np.int64)
    rot = np.argmin(f, axis=1)
    f = np.stack([f[np.arange(len(f)), (rot + k) % 3] for k in range(3)], axis=1)  # keeps the winding
    f = f[np.lexsort((f[:, 1], f[:, 0]))]
    d = np.empty_like(f)
    d[:, 0] = np.diff(f[:, 0], prepend=0)
    d[:, 2] = f[:, 2] - f[:, 0]
    same = np.r_[False, f[1:, 0] == f[:-1, 0]]
    d[:, 1] = np.where(same, f[:, 1] - np.r_[0, f[:-1, 1]], f[:, 1] - f[:, 0])
    return (d % (1 << 32)).astype(np.uint32)


def write_ctm(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None, method: str = "MG1") -> bytes:
    """OpenCTM bytes of a mesh: vertices (n, 3), faces (t, 3) int, per-vertex uv (n, 2) or None."""
    v = np.ascontiguousarray(vertices, np.float32)
    f = np.asarray(faces, np.int64)
    head = b"OCTM" + struct.pack("<i", 5) + method.encode().ljust(4, b"\0")
    head += struct.pack("<5i", len(v), len(f), 0 if uv is None else 1, 0, 0) + _string("ms3d synth")
    if method == "RAW":
        body = b"INDX" + f.astype("<u4").tobytes() + b"VERT" + v.astype("<f4").tobytes()
        if uv is not None:
            body += b"TEXC" + _string("uv") + _string("") + np.asarray(uv, "<f4").tobytes()
    elif method == "MG1":
        body = b"INDX" + _pack(_mg1_deltas(f)) + b"VERT" + _pack(v.view(np.uint32).reshape(-1, 1))
        if uv is not None:
            body += b"TEXC" + _string("uv") + _string("") + _pack(np.asarray(uv, np.float32).view(np.uint32).reshape(-1, 1))
    else:
        raise ValueError(f"unknown OpenCTM method {method!r}")
    return head + body


def _jpeg(image: np.ndarray) -> bytes:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(image, np.uint8)).save(buf, format="JPEG", quality=90)
    return buf.getvalue()


def write_3mxb(path: Path, nodes: list[dict], resources: list[tuple[dict, bytes]]) -> None:
    """A ``.3mxb`` node file: nodes (header dicts), resources (header dict without size, bytes)."""
    res = [dict(r, size=len(b)) for r, b in resources]
    header = json.dumps({"version": 1, "nodes": nodes, "resources": res}).encode()
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"3MXBO" + struct.pack("<I", len(header)) + header + b"".join(b for _, b in resources))


def _node_resources(name: str, v: np.ndarray, f: np.ndarray, uv: np.ndarray | None, jpeg: bytes | None,
                    method: str) -> tuple[dict, list[tuple[dict, bytes]]]:
    """(node dict without children, its resources) for one piece of mesh (faces re-indexed)."""
    used, inv = np.unique(f, return_inverse=True)
    vv, ff = v[used], inv.reshape(-1, 3)
    resources = []
    geom = {"type": "geometryBuffer", "format": "ctm", "id": f"{name}-geometry",
            "bbMin": vv.min(0).tolist(), "bbMax": vv.max(0).tolist()}
    if jpeg is not None and uv is not None:
        resources.append(({"type": "textureBuffer", "format": "jpg", "id": f"{name}-texture"}, jpeg))
        geom["texture"] = f"{name}-texture"
    resources.append((geom, write_ctm(vv, ff, None if uv is None else uv[used], method)))
    node = {"id": name, "bbMin": vv.min(0).tolist(), "bbMax": vv.max(0).tolist(), "maxScreenDiameter": 512.0,
            "resources": [r["id"] for r, _ in resources if r["type"] == "geometryBuffer"]}
    return node, resources


def write_production(out: str | Path, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None = None,
                     texture: np.ndarray | None = None, srs: str = "EPSG:32650",
                     origin: tuple[float, float, float] = (0.0, 0.0, 0.0), n_split: int = 2,
                     coarse_step: int = 4, method: str = "MG1") -> Path:
    """Write a 3MX production of a mesh (vertices (n, 3) metres from ``origin``; faces (t, 3); per-vertex
    uv (n, 2) and a texture image (H, W, 3) uint8, optional) under ``out``; returns the ``.3mx`` scene path."""
    out = Path(out)
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    jpeg = None if texture is None else _jpeg(texture)
    c = v[f].mean(axis=1)
    lo, hi = c[:, :2].min(0), c[:, :2].max(0) + 1e-9
    cell = np.minimum(((c[:, :2] - lo) / (hi - lo) * n_split).astype(int), n_split - 1)
    key = cell[:, 0] * n_split + cell[:, 1]
    children = []
    for k in np.unique(key):
        name = f"Tile_{k}"
        node, res = _node_resources(f"{name}_L2", v, f[key == k], uv, jpeg, method)
        node["children"] = []
        write_3mxb(out / "Data" / name / f"{name}_L2.3mxb", [node], res)
        children.append(f"{name}/{name}_L2.3mxb")
    root, res = _node_resources("root_L1", v, f[::coarse_step], uv, jpeg, method)
    root["children"] = children
    write_3mxb(out / "Data" / "Root.3mxb", [root], res)
    scene = {"3mxVersion": 1, "name": "ms3d synth production", "description": "", "logo": "",
             "sceneOptions": [{"navigation_mode": "PAN"}],
             "layers": [{"type": "meshPyramid", "id": "mesh0", "name": "mesh", "description": "",
                         "SRS": srs, "SRSOrigin": list(map(float, origin)), "root": "Data/Root.3mxb"}]}
    path = out / "Production.3mx"
    path.write_text(json.dumps(scene, indent=1))
    return path


__all__ = ["write_3mxb", "write_ctm", "write_production"]
