"""Texture images embedded in a mesh container, as file references: ``<container>#<image key>``.

The glTF / GLB reader names an embedded image ``<file.glb>#image<k>``, the 3MXB reader
``<node.3mxb>#<texture id>``, the 3D Tiles reader ``<content.b3dm>#image<k>`` (or the glb's own). Stores and
tile meshes keep such references like image paths; :func:`extract_embedded` writes the image's pixels to a
PNG in this process's input cache (``$MS3D_CACHE/inputs/embedded/``, named by the reference and the
container's content fingerprint, written once, atomically) so every reader of image files can open it.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from storage.errors import InputError
from storage.inputs.location import split_embedded


def _pixels(container: Path, ref: str):
    suffix = container.suffix.lower()
    if suffix == ".b3dm":
        from storage.formats.tiles3d import read_content

        mesh = read_content(container)
    elif suffix == ".3mxb":
        from storage.formats.threemx import read_3mx

        mesh = read_3mx(container)
    else:
        from storage.formats.gltf import read_gltf

        mesh = read_gltf(container)
    pixels = mesh.embedded_textures.get(ref)
    if pixels is None:
        raise InputError(container, f"no embedded image {ref.rpartition('#')[2]!r}")
    return pixels


def extract_embedded(ref: str) -> Path:
    """A PNG file holding the pixels of the embedded image ``ref`` (module doc). Raises InputError naming the
    container when it or the image is missing."""
    from PIL import Image

    from storage.atomic import atomic_path
    from storage.inputs.identity import fingerprint
    from storage.inputs.remote import cache_root

    container, _ = split_embedded(ref)
    c = Path(container)
    if not c.is_file():
        raise InputError(c, "the file holding an embedded texture is gone")
    digest = hashlib.sha256(f"{ref}\n{fingerprint(c)}".encode()).hexdigest()[:24]
    out = cache_root() / "embedded" / f"{digest}.png"
    if not out.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        pixels = _pixels(c, ref)
        with atomic_path(out) as tmp:
            Image.fromarray(pixels).save(tmp, format="PNG")
    return out


def resolve_ref(ref) -> str:
    """A local path to open an image reference: an embedded image extracted (:func:`extract_embedded`), an
    input by URL staged (:func:`storage.inputs.remote.readable`), a path as it is."""
    from storage.inputs.remote import is_url, readable

    if split_embedded(ref) is not None and not is_url(str(ref)):
        return str(extract_embedded(str(ref)))
    return readable(ref)


__all__ = ["extract_embedded", "resolve_ref", "split_embedded"]
