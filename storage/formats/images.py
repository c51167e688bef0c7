"""Image files (JPEG, PNG, anything PIL reads): decoded whole or at reduced size, and an atlas cropped,
downscaled and re-encoded for embedding in a glb. A path may name an input by URL (staged first,
:func:`storage.inputs.remote.readable`) where noted.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import numpy as np
from PIL import Image

from storage.formats.embedded import resolve_ref as readable  # URLs staged, embedded images extracted


def read_rgb(path: str | Path) -> np.ndarray:
    """(h, w, 3) uint8 RGB pixels of an image file."""
    return np.asarray(Image.open(path).convert("RGB"))


def read_rgb_reduced(path: str, max_side: int) -> np.ndarray:
    """(h, w, 3) uint8 RGB of an image (a local path or a URL), decoded at about ``max_side`` pixels on its
    longer side where the format allows (JPEG's DCT scaling), else whole. Raises OSError or InputError."""
    im = Image.open(readable(path))
    im.draft("RGB", (max_side, max_side))
    return np.asarray(im.convert("RGB"))


def decode_rgb(data: bytes) -> np.ndarray:
    """(h, w, 3) uint8 RGB pixels of encoded image bytes (JPEG, PNG, ...)."""
    with Image.open(io.BytesIO(data)) as im:
        return np.asarray(im.convert("RGB"))


def encode_rgb(pixels: np.ndarray, fmt: str = "JPEG", quality: int = 85) -> bytes:
    """Encoded bytes (``fmt``: JPEG or PNG) of (h, w, 3) uint8 RGB pixels."""
    buf = io.BytesIO()
    Image.fromarray(pixels).save(buf, format=fmt, **({"quality": int(quality)} if fmt == "JPEG" else {}))
    return buf.getvalue()


def resize_rgb(pixels: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width, 3) uint8: ``pixels`` resampled bilinearly."""
    return np.asarray(Image.fromarray(pixels).resize((int(width), int(height)), Image.BILINEAR))


def embedded_texture(path: str, uv: np.ndarray, max_px: int, quality: int, multiple_of: int = 1
                     ) -> tuple[bytes, str, np.ndarray, np.ndarray]:
    """Crop an atlas (a local path or a URL) to the pixels ``uv`` (k, 2) (glTF convention) use, downscale to
    ``max_px``, encode. Returns (the image's bytes, their MIME type, its pixels (H, W, 3) uint8, uv remapped
    to the new image (k, 2) float32). The file's own bytes are embedded when neither crop nor downscale is
    needed. ``multiple_of``: each side rounded up to a multiple of it (4 for block-compressed KTX2 / Basis
    textures; uv are relative, so a resize keeps them)."""
    path = readable(path)  # a texture of an input named by URL: staged in this process's cache
    with Image.open(path) as im:
        fmt, (w0, h0) = im.format, im.size
        x0 = max(0, math.floor(float(uv[:, 0].min()) * w0) - 2) if len(uv) else 0
        x1 = min(w0, math.ceil(float(uv[:, 0].max()) * w0) + 2) if len(uv) else w0
        y0 = max(0, math.floor(float(uv[:, 1].min()) * h0) - 2) if len(uv) else 0
        y1 = min(h0, math.ceil(float(uv[:, 1].max()) * h0) + 2) if len(uv) else h0
        cw, ch = max(1, x1 - x0), max(1, y1 - y0)
        scale = min(1.0, max_px / max(cw, ch))
        whole = (x0, y0, x1, y1) == (0, 0, w0, h0)
        if fmt == "JPEG" and scale < 1.0:
            im.draft("RGB", (math.ceil(w0 * scale), math.ceil(h0 * scale)))  # decode at 1/2, 1/4.. directly
        f = im.size[0] / w0
        rgb = im if im.mode == "RGB" else im.convert("RGB")  # no full-size copy of an RGB atlas
        if not whole:
            rgb = rgb.crop((math.floor(x0 * f), math.floor(y0 * f), math.ceil(x1 * f), math.ceil(y1 * f)))
        if rgb is not im:
            im.close()  # frees the decoded atlas now, not at the end of the block
        size = (max(1, round(cw * scale)), max(1, round(ch * scale)))
        if multiple_of > 1:
            size = tuple(-(-v // multiple_of) * multiple_of for v in size)
        if rgb.size != size:
            rgb = rgb.resize(size, Image.BILINEAR)
        if whole and scale == 1.0 and rgb.size == (w0, h0) and fmt in ("JPEG", "PNG"):
            data, mime = Path(path).read_bytes(), "image/jpeg" if fmt == "JPEG" else "image/png"
        else:
            buf = io.BytesIO()
            if fmt == "PNG":
                rgb.save(buf, format="PNG", compress_level=3)
                mime = "image/png"
            else:
                rgb.save(buf, format="JPEG", quality=quality)
                mime = "image/jpeg"
            data = buf.getvalue()
        pixels = np.asarray(rgb)
    new_uv = np.empty_like(uv, dtype=np.float32)
    new_uv[:, 0] = (uv[:, 0] * w0 - x0) / cw
    new_uv[:, 1] = (uv[:, 1] * h0 - y0) / ch
    return data, mime, pixels, new_uv


__all__ = ["embedded_texture", "read_rgb", "read_rgb_reduced"]
