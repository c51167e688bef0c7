"""3D Tiles tilesets as a mesh input: ``tileset.json`` (1.0 or 1.1) with glb or b3dm content.

A tileset is read at its finest level: the content of every tile without children (of the tileset and of
the external tilesets its contents name), each content's positions taken through the chain 3D Tiles
defines: glTF node transforms, glTF's Y-up to Z-up (:func:`storage.formats.gltf.y_up_to_z_up`), a b3dm's
``RTC_CENTER``, then the tile transforms from the root down. The result is one :class:`MeshData` whose
vertices are **ECEF metres** (EPSG:4978, float64); the scan and ingest stages place it into the campus CRS
(``tasks.scan.placement``: a tileset needs ``inputs.crs``). Textures embedded in the content are kept as
references (``<content.glb>#imageK``, resolved on demand by :mod:`storage.formats.embedded`), not decoded:
memory holds the geometry and one content's pixels at a time.

Refused with one line naming the file: a JSON that is not a tileset, point-cloud / instanced / composite
content (``.pnts``, ``.i3dm``, ``.cmpt``), implicit tiling other than QUADTREE, a content file that is missing or not a GLB /
b3dm, and a tileset with no content. Draco-compressed glb (``KHR_draco_mesh_compression``) is decoded by the
glTF reader only where trimesh can; otherwise it is refused naming the file.
"""

from __future__ import annotations

import json
import struct
import tempfile
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.mesh_data import MeshData
from storage.formats.srs import ecef_to_crs

B3DM_HEADER = 28
MAX_DEPTH = 64  # external tilesets nested deeper than this are a loop


def is_tileset(path: str | Path) -> bool:
    """Whether ``path`` names a 3D Tiles tileset (a ``.json`` file; its content decides when read)."""
    return Path(path).suffix.lower() == ".json"


def _load_json(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "tileset file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise InputError(path, f"not a readable JSON file ({e})") from None
    if not isinstance(doc, dict) or "asset" not in doc or not isinstance(doc.get("root"), dict):
        raise InputError(path, "not a 3D Tiles tileset (no 'asset' and 'root')")
    return doc


def _matrix(tile: dict, path: Path) -> np.ndarray:
    t = tile.get("transform")
    if t is None:
        return np.eye(4)
    m = np.asarray(t, np.float64)
    if m.shape != (16,) or not np.isfinite(m).all():
        raise InputError(path, "a tile transform is not 16 finite numbers")
    return m.reshape(4, 4).T  # column-major in the file


def _contents(tile: dict) -> list[str]:
    out = []
    if isinstance(tile.get("content"), dict):
        out.append(tile["content"].get("uri") or tile["content"].get("url"))
    for c in tile.get("contents") or []:
        out.append(c.get("uri"))
    return [u for u in out if u]


def _leaves(path: Path, doc: dict, parent: np.ndarray, depth: int, out: list) -> None:
    """Collect (content path, tile-to-ECEF matrix) of the finest level, recursing into external tilesets."""
    if depth > MAX_DEPTH:
        raise InputError(path, "external tilesets nest deeper than 64 levels (a loop?)")
    stack = [(doc["root"], parent)]
    while stack:
        tile, m_parent = stack.pop()
        if "implicitTiling" in tile:
            tile = _expanded(path, tile)
        m = m_parent @ _matrix(tile, path)
        children = tile.get("children") or []
        for uri in _contents(tile):
            if "{" in uri:
                raise InputError(path, f"content uri {uri!r} is a template (implicit tiling): not read")
            target = (path.parent / uri.split("?")[0]).resolve()
            if target.suffix.lower() == ".json":  # an external tileset: its root continues this tile
                _leaves(target, _load_json(target), m, depth + 1, out)
            elif not children:
                out.append((target, m))
        for child in children:
            stack.append((child, m))


def _expanded(path: Path, tile: dict) -> dict:
    """An implicit tile (QUADTREE) as explicit tiles: its subtrees read next to ``path``."""
    from storage.formats.implicit_tiling import expand_implicit

    def read(name: str) -> bytes:
        try:
            return (path.parent / name).read_bytes()
        except OSError as e:
            raise InputError(path, f"subtree {name} not readable ({e.strerror or e})") from None

    try:
        return expand_implicit({"root": tile}, read)["root"]
    except InputError as e:  # a subtree's problem names the subtree (relative to the tileset) or the tileset
        if e.path is not None and Path(e.path).is_absolute():
            raise
        raise InputError(path.parent / e.path if e.path else path, e.problem) from None
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(path, f"implicit tiling not understood ({type(e).__name__}: {e})") from None


def _b3dm_glb(path: Path) -> tuple[bytes, np.ndarray]:
    """(the glb bytes, RTC_CENTER (3,) float64 or zeros) of a b3dm file."""
    data = path.read_bytes()
    if len(data) < B3DM_HEADER or data[:4] != b"b3dm":
        raise InputError(path, "not a b3dm file (missing 'b3dm' magic)")
    _, length, ft_json, ft_bin, bt_json, bt_bin = struct.unpack("<6I", data[4:B3DM_HEADER])
    if length > len(data):
        raise InputError(path, f"truncated b3dm: header says {length:,} bytes, file has {len(data):,}")
    start = B3DM_HEADER + ft_json + ft_bin + bt_json + bt_bin
    rtc = np.zeros(3)
    if ft_json:
        try:
            table = json.loads(data[B3DM_HEADER:B3DM_HEADER + ft_json].decode("utf-8").rstrip(" \x00"))
        except (UnicodeDecodeError, json.JSONDecodeError) as e:
            raise InputError(path, f"unreadable feature table ({e})") from None
        c = table.get("RTC_CENTER")
        if isinstance(c, list) and len(c) == 3:
            rtc = np.asarray(c, np.float64)
        elif isinstance(c, dict):  # a binary reference
            off = B3DM_HEADER + ft_json + int(c.get("byteOffset", 0))
            rtc = np.frombuffer(data[off:off + 24], "<f8").astype(np.float64)
    glb = data[start:length]
    if glb[:4] != b"glTF":
        raise InputError(path, "the b3dm's embedded glTF is missing or not binary")
    return glb, rtc


def _renamed_textures(mesh: MeshData, old: str, new: str) -> MeshData:
    """Texture references of a b3dm's glb (read from a scratch copy) named after the b3dm itself, so they
    stay resolvable (:mod:`storage.formats.embedded`) once the scratch copy is gone."""
    rename = lambda t: new + t[len(old):] if t.startswith(old) else t
    mesh.textures = [rename(t) for t in mesh.textures]
    mesh.embedded_textures = {rename(k): v for k, v in mesh.embedded_textures.items()}
    return mesh


def read_content(path: str | Path) -> MeshData:
    """One tile content file (glb or b3dm) in its tile frame (Z-up, RTC_CENTER applied; no tile transform)."""
    path = Path(path).absolute()
    with tempfile.TemporaryDirectory(prefix="ms3d-b3dm-") as tmp:
        return _read_content(path, np.eye(4), Path(tmp), 0)


def _read_content(path: Path, matrix: np.ndarray, scratch: Path, k: int) -> MeshData:
    from storage.formats.gltf import read_gltf

    if not path.is_file():
        raise InputError(path, "tile content not found")
    suffix = path.suffix.lower()
    if suffix in (".pnts", ".i3dm", ".cmpt"):
        raise InputError(path, f"{suffix} content (points / instances / composite) is not a mesh: not read")
    rtc = np.zeros(3)
    if suffix == ".b3dm":
        glb, rtc = _b3dm_glb(path)
        local = scratch / f"{k:06d}-{path.stem}.glb"
        local.write_bytes(glb)
        mesh = _renamed_textures(read_gltf(local), f"{local.resolve()}#", f"{path}#")
    elif suffix in (".glb", ".gltf"):
        mesh = read_gltf(path)
    else:
        raise InputError(path, f"tile content {suffix or 'without extension'} is not glb or b3dm: not read")
    v = mesh.vertices + rtc
    mesh.vertices = v @ matrix[:3, :3].T + matrix[:3, 3]
    return mesh


def _without_pixels(mesh: MeshData) -> MeshData:
    """The mesh with its texture references but not their decoded pixels: a whole tileset's atlases would
    not fit in memory, and every reference stays resolvable from its content file
    (:func:`storage.formats.embedded.resolve_ref`)."""
    mesh.embedded_textures = {}
    return mesh


def read_tileset(path: str | Path) -> MeshData:
    """The finest level of a 3D Tiles tileset as one mesh, vertices in ECEF metres (module doc).
    Raises InputError naming the tileset or the content file at fault."""
    path = Path(path).absolute()
    doc = _load_json(path)
    leaves: list = []
    _leaves(path, doc, np.eye(4), 0, leaves)
    if not leaves:
        raise InputError(path, "the tileset names no mesh content")
    leaves.sort(key=lambda pm: str(pm[0]))  # file order, whatever the tree's
    with tempfile.TemporaryDirectory(prefix="ms3d-b3dm-") as tmp:
        parts = [_without_pixels(_read_content(p, m, Path(tmp), k)) for k, (p, m) in enumerate(leaves)]
    return MeshData.concat(parts, source=str(path))


__all__ = ["ecef_to_crs", "is_tileset", "read_content", "read_tileset"]  # ecef_to_crs: storage.formats.srs
