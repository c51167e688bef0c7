"""COLMAP sparse models, text and binary, as :class:`storage.formats.cameras.CameraSet` in the OpenCV convention of
:mod:`storage.formats.cameras` (pixel centres at integers; world-to-camera R, t); and the rotation <-> quaternion
conversions they use. Registered in :mod:`storage.formats.camera_files`.

COLMAP (``cameras.txt``: ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``; ``images.txt``: per image one line
``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME`` then one line of 2D points, possibly empty). The quaternion
(Hamilton, w first) and t map world to camera. Models: SIMPLE_PINHOLE (f cx cy), PINHOLE (fx fy cx cy),
SIMPLE_RADIAL (f cx cy k), RADIAL (f cx cy k1 k2), OPENCV (fx fy cx cy k1 k2 p1 p2) and FULL_OPENCV when its
rational terms k4..k6 are 0. COLMAP's principal point counts from the image corner: cx = cx_colmap - 0.5.
COLMAP's binary model (``cameras.bin``, ``images.bin``: COLMAP's default output) is read the same way when
the folder has no text model: little-endian, ``cameras.bin`` = uint64 count, then per camera uint32 id,
int32 model id, uint64 width, height, float64 params; ``images.bin`` = uint64 count, then per image uint32
id, float64 qw qx qy qz tx ty tz, uint32 camera id, a NUL-terminated name, uint64 number of 2D points and
that many (float64 x, y, int64 point id).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.cameras import Camera, CameraSet, check_pose

# ------------------------------------------------------------------------------------- rotations


def quat_to_rot(q) -> np.ndarray:
    """(qw, qx, qy, qz) -> (3, 3) float64 rotation (normalised first).

    >>> quat_to_rot([0.0, 0.0, 0.0, 1.0]).round(6).tolist()  # 180 deg about z
    [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    w, x, y, z = np.asarray(q, np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def rot_to_quat(r: np.ndarray) -> np.ndarray:
    """(3, 3) rotation -> (4,) float64 (qw, qx, qy, qz), qw >= 0; from the largest diagonal term (stable)."""
    r = np.asarray(r, np.float64)
    tr = np.trace(r)
    cands = [tr, r[0, 0], r[1, 1], r[2, 2]]
    i = int(np.argmax(cands))
    if i == 0:
        s = 2.0 * np.sqrt(1.0 + tr)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        a, b, c = [(0, 1, 2), (1, 2, 0), (2, 0, 1)][i - 1]
        s = 2.0 * np.sqrt(1.0 + r[a, a] - r[b, b] - r[c, c])
        q = np.zeros(4)
        q[0] = (r[c, b] - r[b, c]) / s
        q[1 + a] = 0.25 * s
        q[1 + b] = (r[a, b] + r[b, a]) / s
        q[1 + c] = (r[a, c] + r[c, a]) / s
    q = np.asarray(q, np.float64)
    return q if q[0] >= 0 else -q


# ------------------------------------------------------------------------------------- COLMAP

_COLMAP = {"SIMPLE_PINHOLE": 3, "PINHOLE": 4, "SIMPLE_RADIAL": 4, "RADIAL": 5, "OPENCV": 8, "FULL_OPENCV": 12}


def _colmap_intrinsics(model: str, p: list[float]) -> tuple[np.ndarray, np.ndarray] | str:
    """(K, dist) from a COLMAP model's parameters, or a message saying why not."""
    if model not in _COLMAP:
        return f"camera model {model} is not supported (use {', '.join(_COLMAP)})"
    if len(p) != _COLMAP[model]:
        return f"{model} takes {_COLMAP[model]} parameters, got {len(p)}"
    d = np.zeros(5)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = p[0]
        cx, cy = p[1], p[2]
        d[: len(p) - 3] = p[3:]  # k1 (and k2)
    else:
        fx, fy, cx, cy = p[:4]
        if model in ("OPENCV", "FULL_OPENCV"):
            d[:4] = p[4:8]
        if model == "FULL_OPENCV":
            if any(v != 0 for v in p[9:12]):
                return "FULL_OPENCV with rational terms k4..k6 is not supported"
            d[4] = p[8]
    return np.array([[fx, 0.0, cx - 0.5], [0.0, fy, cy - 0.5], [0.0, 0.0, 1.0]]), d


def _colmap_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read ({e})") from None
    return [(i + 1, s) for i, s in enumerate(text.splitlines()) if not s.lstrip().startswith("#")]


def _floats(path: Path, lineno: int, tokens: list[str]) -> list[float]:
    try:
        vals = [float(v) for v in tokens]
    except ValueError:
        raise InputError(path, f"line {lineno}: not a number in {' '.join(tokens)!r}") from None
    if not np.isfinite(vals).all():
        raise InputError(path, f"line {lineno}: NaN or infinite value")
    return vals


COLMAP_FILES = ("images.txt", "cameras.txt")  # a COLMAP text model's files ms3d reads (and fingerprints)
COLMAP_BIN_FILES = ("images.bin", "cameras.bin")  # the binary model's, read when the text files are absent
_MODEL_IDS = {0: "SIMPLE_PINHOLE", 1: "PINHOLE", 2: "SIMPLE_RADIAL", 3: "RADIAL", 4: "OPENCV", 5: "OPENCV_FISHEYE",
              6: "FULL_OPENCV", 7: "FOV", 8: "SIMPLE_RADIAL_FISHEYE", 9: "RADIAL_FISHEYE", 10: "THIN_PRISM_FISHEYE"}
_MODEL_PARAMS = {0: 3, 1: 4, 2: 4, 3: 5, 4: 8, 5: 8, 6: 12, 7: 5, 8: 4, 9: 5, 10: 12}


def is_colmap(path: str | Path) -> bool:
    """Whether a camera path names a COLMAP model: its folder, or one of its cameras / images files (.txt
    or .bin)."""
    p = Path(path)
    return p.is_dir() or p.name.lower() in COLMAP_FILES + COLMAP_BIN_FILES


def camera_files(path: str | Path) -> list[Path]:
    """The files a camera path stands for: a COLMAP model's images.txt and cameras.txt (in that order, from
    its folder), else the file itself.

    >>> [p.name for p in camera_files("sparse/0/cameras.txt")], [p.name for p in camera_files("cams.json")]
    (['images.txt', 'cameras.txt'], ['cams.json'])
    """
    p = Path(path)
    return _colmap_model(p) if is_colmap(p) else [p]


def _colmap_model(path: Path) -> list[Path]:
    """The model's (images, cameras) files: the text ones, or the binary ones when the folder has them and
    no text model."""
    folder = path if path.is_dir() else path.parent
    text = [folder / name for name in COLMAP_FILES]
    binary = [folder / name for name in COLMAP_BIN_FILES]
    if not any(p.is_file() for p in text) and any(p.is_file() for p in binary):
        return binary
    return text


def _colmap_files(path: Path) -> tuple[Path, Path]:
    imgs, cams = _colmap_model(path)
    kind = "binary" if imgs.suffix == ".bin" else "text"
    for p in (cams, imgs):
        if not p.is_file():
            raise InputError(p, f"COLMAP {kind} model incomplete: {p.name} not found")
    return cams, imgs


class _Bin:
    """A little-endian reader over a COLMAP binary file; InputError naming it when it ends early."""

    def __init__(self, path: Path):
        self.path = path
        try:
            self.data = path.read_bytes()
        except OSError as e:
            raise InputError(path, f"cannot read ({e.strerror})") from None
        self.pos = 0

    def take(self, fmt: str):
        import struct

        n = struct.calcsize("<" + fmt)
        if self.pos + n > len(self.data):
            raise InputError(self.path, f"truncated at byte {self.pos:,} of {len(self.data):,}")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += n
        return out

    def name(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise InputError(self.path, f"truncated image name at byte {self.pos:,}")
        raw, self.pos = self.data[self.pos:end], end + 1
        return raw.decode("utf-8", errors="replace")


def _read_colmap_bin(cams_bin: Path, imgs_bin: Path) -> CameraSet:
    """A COLMAP binary model (module doc)."""
    b = _Bin(cams_bin)
    intr = {}
    for k in range(b.take("Q")[0]):
        cam_id, model_id, w, h = b.take("IiQQ")
        if model_id not in _MODEL_PARAMS:
            raise InputError(cams_bin, f"camera {cam_id}: unknown model id {model_id}")
        params = list(b.take(f"{_MODEL_PARAMS[model_id]}d"))
        if not np.isfinite(params).all():
            raise InputError(cams_bin, f"camera {cam_id}: NaN or infinite parameter")
        got = _colmap_intrinsics(_MODEL_IDS[model_id], params)
        if isinstance(got, str):
            raise InputError(cams_bin, f"camera {cam_id}: {got}")
        intr[cam_id] = (got, int(w), int(h))
    b = _Bin(imgs_bin)
    out = []
    for _ in range(b.take("Q")[0]):
        image_id, *v = b.take("I7d")
        (cam_id,) = b.take("I")
        name = b.name()
        (n2d,) = b.take("Q")
        if b.pos + 24 * n2d > len(b.data):
            raise InputError(imgs_bin, f"image {image_id}: truncated 2D points")
        b.pos += 24 * n2d
        if not np.isfinite(v).all():
            raise InputError(imgs_bin, f"image {image_id}: NaN or infinite pose")
        if cam_id not in intr:
            raise InputError(imgs_bin, f"image {image_id}: camera {cam_id} is not in {cams_bin.name}")
        (K, d), w, h = intr[cam_id]
        if np.linalg.norm(v[:4]) < 1e-9:
            raise InputError(imgs_bin, f"image {image_id}: zero quaternion")
        out.append(check_pose(imgs_bin, name, K, quat_to_rot(v[:4]), v[4:7], w, h, d))
    if not out:
        raise InputError(imgs_bin, "no images in the COLMAP model")
    return CameraSet(out, "mesh", (0.0, 0.0, 0.0), "colmap")


def read_colmap(path: Path) -> CameraSet:
    """A COLMAP sparse model, text or binary: ``path`` is its folder or one of its files."""
    cams_txt, imgs_txt = _colmap_files(Path(path))
    if cams_txt.suffix == ".bin":
        return _read_colmap_bin(cams_txt, imgs_txt)
    intr = {}
    for lineno, line in _colmap_lines(cams_txt):
        tok = line.split()
        if not tok:
            continue
        if len(tok) < 4:
            raise InputError(cams_txt, f"line {lineno}: expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS...")
        vals = _floats(cams_txt, lineno, [tok[0], *tok[2:]])
        got = _colmap_intrinsics(tok[1].upper(), vals[3:])
        if isinstance(got, str):
            raise InputError(cams_txt, f"line {lineno}: {got}")
        intr[tok[0]] = (got, int(vals[1]), int(vals[2]))
    out = []
    lines = _colmap_lines(imgs_txt)
    i = 0
    while i < len(lines):
        lineno, line = lines[i]
        tok = line.split()
        if not tok:
            i += 1
            continue
        if len(tok) < 10:
            raise InputError(imgs_txt, f"line {lineno}: expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME "
                                       f"(truncated?)")
        v = _floats(imgs_txt, lineno, tok[1:8])
        if tok[8] not in intr:
            raise InputError(imgs_txt, f"line {lineno}: camera {tok[8]} is not in {cams_txt.name}")
        (K, d), w, h = intr[tok[8]]
        if np.linalg.norm(v[:4]) < 1e-9:
            raise InputError(imgs_txt, f"line {lineno}: zero quaternion")
        out.append(check_pose(imgs_txt, " ".join(tok[9:]), K, quat_to_rot(v[:4]), v[4:7], w, h, d))
        i += 2  # the image line and its 2D-points line (which may be empty)
    if not out:
        raise InputError(imgs_txt, "no images in the COLMAP model")
    return CameraSet(out, "mesh", (0.0, 0.0, 0.0), "colmap")


def write_colmap_bin(folder: Path, cams: list[Camera], points_per_image: int = 3) -> None:
    """Write ``cams`` as a COLMAP binary model (one OPENCV / FULL_OPENCV camera per image, as
    :func:`write_colmap`), each image with ``points_per_image`` dummy 2D points (for tests)."""
    import struct

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cb, ib = [struct.pack("<Q", len(cams))], [struct.pack("<Q", len(cams))]
    for i, c in enumerate(cams, start=1):
        k1, k2, p1, p2, k3 = np.asarray(c.dist, np.float64)
        p = [c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5, k1, k2, p1, p2]
        model = 4 if k3 == 0 else 6
        if k3 != 0:
            p += [k3, 0.0, 0.0, 0.0]
        cb.append(struct.pack("<IiQQ", i, model, c.width, c.height) + struct.pack(f"<{len(p)}d", *p))
        ib.append(struct.pack("<I7dI", i, *rot_to_quat(c.R), *c.t, i) + c.image.encode() + b"\x00"
                  + struct.pack("<Q", points_per_image)
                  + b"".join(struct.pack("<ddq", 1.5 * k, 2.5 * k, -1) for k in range(points_per_image)))
    (folder / "cameras.bin").write_bytes(b"".join(cb))
    (folder / "images.bin").write_bytes(b"".join(ib))


def write_colmap(folder: Path, cams: list[Camera]) -> None:
    """Write ``cams`` as a COLMAP text model (one OPENCV camera per image; FULL_OPENCV when k3 != 0)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    cl, il = ["# Camera list: CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"], ["# Image list"]
    for i, c in enumerate(cams, start=1):
        k1, k2, p1, p2, k3 = np.asarray(c.dist, np.float64)
        p = [c.K[0, 0], c.K[1, 1], c.K[0, 2] + 0.5, c.K[1, 2] + 0.5, k1, k2, p1, p2]
        model = "OPENCV" if k3 == 0 else "FULL_OPENCV"
        if k3 != 0:
            p += [k3, 0.0, 0.0, 0.0]
        cl.append(f"{i} {model} {c.width} {c.height} " + " ".join(repr(float(x)) for x in p))
        q = rot_to_quat(c.R)
        il.append(f"{i} " + " ".join(repr(float(x)) for x in (*q, *c.t)) + f" {i} {c.image}")
        il.append("")
    (folder / "cameras.txt").write_text("\n".join(cl) + "\n")
    (folder / "images.txt").write_text("\n".join(il) + "\n")


__all__ = ["COLMAP_BIN_FILES", "COLMAP_FILES", "camera_files", "is_colmap", "quat_to_rot", "read_colmap", "rot_to_quat",
           "write_colmap", "write_colmap_bin"]
