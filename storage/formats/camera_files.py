"""Camera files: the registry of camera readers (:func:`read_cameras`) and the ContextCapture / iTwin Capture
BlocksExchange XML; the COLMAP models are read by :mod:`storage.formats.colmap` (re-exported here). Both give
:class:`storage.formats.cameras.CameraSet` in the OpenCV convention of :mod:`storage.formats.cameras` (pixel centres
at integers; world-to-camera R, t).

BlocksExchange: ``Block/Photogroups/Photogroup`` with ``ImageDimensions`` (Width, Height), ``FocalLengthPixels``
or ``FocalLength`` (mm) with ``SensorSize`` (mm, the larger image side), ``PrincipalPoint`` (x, y pixels, taken
with pixel centres at integers), ``AspectRatio`` (fy / fx), ``Skew`` (pixels), ``Distortion`` (K1 K2 K3 P1 P2,
taken as OpenCV's), ``CameraOrientation`` (XRightYDown or XRightYUp) and ``Photo`` (``ImagePath``, ``Pose``:
``Rotation`` M_00..M_22 world-to-camera, ``Center`` x y z). Photos without a rotation matrix and centre are
skipped and counted (``CameraSet.skipped``). ``BaseImagePath`` prefixes relative image paths.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.cameras import Camera, CameraSet, check_pose, read_cameras_json
from storage.formats.colmap import (
    COLMAP_FILES,
    camera_files,
    is_colmap,
    quat_to_rot,
    read_colmap,
    rot_to_quat,
    write_colmap,
    write_colmap_bin,
)

# ------------------------------------------------------------------------------------- BlocksExchange

_ORIENT = {"xrightydown": np.eye(3), "xrightyup": np.diag([1.0, -1.0, -1.0])}


def _num(path: Path, el, tag: str, default: float | None = None) -> float:
    node = el.find(tag)
    if node is None or node.text is None or not node.text.strip():
        if default is None:
            raise InputError(path, f"<{el.tag}> has no <{tag}>")
        return default
    try:
        v = float(node.text)
    except ValueError:
        raise InputError(path, f"<{tag}> is not a number: {node.text.strip()!r}") from None
    if not np.isfinite(v):
        raise InputError(path, f"<{tag}> is not finite")
    return v


def _group_intrinsics(path: Path, g) -> tuple[np.ndarray, np.ndarray, int, int, np.ndarray]:
    """(K, dist, width, height, orientation) of a Photogroup."""
    w, h = int(_num(path, g, "ImageDimensions/Width")), int(_num(path, g, "ImageDimensions/Height"))
    if g.find("FocalLengthPixels") is not None:
        f = _num(path, g, "FocalLengthPixels")
    else:
        f = _num(path, g, "FocalLength") * max(w, h) / _num(path, g, "SensorSize")
    cx = _num(path, g, "PrincipalPoint/x", (w - 1) / 2)
    cy = _num(path, g, "PrincipalPoint/y", (h - 1) / 2)
    K = np.array([[f, _num(path, g, "Skew", 0.0), cx], [0.0, f * _num(path, g, "AspectRatio", 1.0), cy],
                  [0.0, 0.0, 1.0]])
    d = np.array([_num(path, g, f"Distortion/{k}", 0.0) for k in ("K1", "K2", "P1", "P2", "K3")])
    orient = (g.findtext("CameraOrientation") or "XRightYDown").strip().lower()
    if orient not in _ORIENT:
        raise InputError(path, f"CameraOrientation {orient!r} is not supported (XRightYDown, XRightYUp)")
    return K, d, w, h, _ORIENT[orient]


def read_blocks_exchange(path: Path) -> CameraSet:
    """Every posed photo of every block of a BlocksExchange XML (module docstring)."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise InputError(path, f"not a readable BlocksExchange XML ({e})") from None
    if root.tag != "BlocksExchange":
        raise InputError(path, f"not a BlocksExchange XML (root element <{root.tag}>)")
    base = (root.findtext("BaseImagePath") or "").strip()
    out, skipped = [], 0
    for g in root.iter("Photogroup"):
        K, d, w, h, orient = _group_intrinsics(path, g)
        for ph in g.findall("Photo"):
            name = (ph.findtext("ImagePath") or "").strip()
            rot, cen = ph.find("Pose/Rotation"), ph.find("Pose/Center")
            if not name or rot is None or cen is None or rot.find("M_00") is None:
                skipped += 1
                continue
            r = orient @ np.array([[_num(path, rot, f"M_{i}{j}") for j in range(3)] for i in range(3)])
            c = np.array([_num(path, cen, a) for a in "xyz"])
            if base and not Path(name).is_absolute() and not name[1:3] == ":\\":
                name = str(Path(base) / name)
            out.append(check_pose(path, name, K, r, -r @ c, w, h, d))
    if not out:
        raise InputError(path, f"no posed photo in the BlocksExchange XML ({skipped} without a pose)")
    srs = root.findtext("SpatialReferenceSystems/SRS/Definition")
    return CameraSet(out, "mesh", (0.0, 0.0, 0.0), "blocksexchange", skipped=skipped,
                     crs=srs.strip() if srs else None)


def write_blocks_exchange(path: Path, cams: list[Camera], crs: str | None = None, focal_mm: bool = False) -> None:
    """Write ``cams`` as a BlocksExchange XML, one Photogroup per camera (focal in pixels, or with
    ``focal_mm`` as FocalLength mm + a 36 mm SensorSize)."""
    root = ET.Element("BlocksExchange", version="2.1")

    def sub(parent, tag, text=None):
        e = ET.SubElement(parent, tag)
        if text is not None:
            e.text = text if isinstance(text, str) else repr(float(text))
        return e

    if crs:
        srs = sub(sub(root, "SpatialReferenceSystems"), "SRS")
        sub(srs, "Id", "0")
        sub(srs, "Definition", crs)
    block = sub(root, "Block")
    if crs:
        sub(block, "SRSId", "0")
    groups = sub(block, "Photogroups")
    for i, c in enumerate(cams):
        g = sub(groups, "Photogroup")
        dims = sub(g, "ImageDimensions")
        sub(dims, "Width", str(c.width))
        sub(dims, "Height", str(c.height))
        if focal_mm:
            sub(g, "FocalLength", c.K[0, 0] * 36.0 / max(c.width, c.height))
            sub(g, "SensorSize", 36.0)
        else:
            sub(g, "FocalLengthPixels", c.K[0, 0])
        sub(g, "CameraOrientation", "XRightYDown")
        pp = sub(g, "PrincipalPoint")
        sub(pp, "x", c.K[0, 2])
        sub(pp, "y", c.K[1, 2])
        sub(g, "AspectRatio", c.K[1, 1] / c.K[0, 0])
        sub(g, "Skew", c.K[0, 1])
        dist = sub(g, "Distortion")
        for k, v in zip(("K1", "K2", "P1", "P2", "K3"), np.asarray(c.dist, np.float64)):
            sub(dist, k, v)
        ph = sub(g, "Photo")
        sub(ph, "Id", str(i))
        sub(ph, "ImagePath", c.image)
        pose = sub(ph, "Pose")
        rot = sub(pose, "Rotation")
        for a in range(3):
            for b in range(3):
                sub(rot, f"M_{a}{b}", c.R[a, b])
        cen = sub(pose, "Center")
        for a, v in zip("xyz", c.centre):
            sub(cen, a, v)
    ET.indent(root)
    ET.ElementTree(root).write(path, encoding="utf-8", xml_declaration=True)


# ------------------------------------------------------------------------------------- dispatch

def camera_format(path: str | Path) -> str:
    """'colmap' (a folder, cameras / images .txt or .bin), 'blocksexchange' (.xml) or 'cameras.json' (.json)."""
    p = Path(path)
    if is_colmap(p):
        return "colmap"
    if p.suffix.lower() == ".xml":
        return "blocksexchange"
    if p.suffix.lower() == ".json":
        return "cameras.json"
    raise InputError(p, "unknown camera file: expected a cameras.json, a COLMAP model (folder with cameras + images "
                        ".txt or .bin) or a ContextCapture BlocksExchange .xml")


CAMERA_READERS = {"colmap": read_colmap, "blocksexchange": read_blocks_exchange, "cameras.json": read_cameras_json}
"""Camera format (:func:`camera_format`) -> its reader; each returns a :class:`CameraSet` or raises InputError."""


def read_cameras(path: str | Path) -> CameraSet:
    """Every camera of a camera file (format by :func:`camera_format`). Raises InputError naming the file
    on anything unreadable: missing, truncated, bad numbers, unknown camera model."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "camera file not found (inputs.cameras in the config)")
    return CAMERA_READERS[camera_format(p)](p)


__all__ = ["CAMERA_READERS", "COLMAP_FILES", "camera_files", "camera_format", "is_colmap", "quat_to_rot",
           "read_blocks_exchange", "read_cameras", "read_colmap", "rot_to_quat", "write_blocks_exchange",
           "write_colmap", "write_colmap_bin"]
