"""Compression of written glb files through glTF-Transform in node (``viewer/compress.mjs``):

- geometry ``meshopt`` (``export.compression: meshopt``): vertex order optimised, positions (16 bits over each
  mesh's bounds), normals, texture coordinates and colours quantized (``KHR_mesh_quantization``), feature ids
  left exact, then ``EXT_meshopt_compression``;
- textures ``etc1s`` / ``uastc`` (``export.texture: ktx2``: ETC1S for LOD parents, UASTC for leaves): KTX2 /
  Basis Universal with mipmaps (``KHR_texture_basisu``), through ktx2-encoder's Basis encoder (WebAssembly).

``EXT_mesh_features`` and ``EXT_structural_metadata`` are kept (glTF-Transform 4.5 registers both). Needs node
and the viewer's npm packages (installed by ``make``).
"""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

from storage.errors import InputError

SCRIPT = Path(__file__).resolve().parents[2] / "viewer" / "compress.mjs"


def compress_glbs(paths: list[Path], geometry: str = "meshopt", texture: str = "keep") -> dict[str, tuple[int, int]]:
    """Compress the glb files ``paths`` in place (geometry "none" / "meshopt"; texture "keep" / "etc1s" /
    "uastc"); returns {path: (bytes before, bytes after)}. Raises InputError (one line) when node or the
    packages are missing or a file cannot be compressed."""
    if not paths:
        return {}
    node = shutil.which("node")
    if node is None or not (SCRIPT.parent / "node_modules" / "@gltf-transform" / "core").is_dir():
        raise InputError(SCRIPT, "export.compression meshopt and export.texture ktx2 need node and the viewer's npm "
                                 "packages (make install, or npm ci --prefix viewer)")
    run = subprocess.run([node, str(SCRIPT), "--geometry", geometry, "--texture", texture, *map(str, paths)],
                         capture_output=True, text=True, check=False, timeout=3600)
    if run.returncode != 0:
        why = (run.stderr.strip().splitlines() or ["no output"])[-1]
        raise InputError(paths[0], f"glb compression ({geometry}, textures {texture}) failed: {why}")
    return {k: tuple(v) for k, v in json.loads(run.stdout.strip().splitlines()[-1]).items()}


__all__ = ["compress_glbs"]
