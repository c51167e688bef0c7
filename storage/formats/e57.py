"""E57 point clouds (ASTM E2807; through pye57 / libE57Format; registered in :mod:`storage.formats.points`).

Every scan of the file is read, its invalid points (``*InvalidState``) dropped, spherical scans converted to
Cartesian, and each scan's pose (rotation quaternion + translation) applied, so all points come out in the
file's common frame: float64 metres. Colours (``colorRed/Green/Blue``) become LAS-style uint16 (8-bit values
scaled), a float ``intensity`` goes to ``extra["intensity"]``, an integer one to ``intensity``. Memory: one
scan at a time (a scan is read whole, then chunked).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.point_chunk import PointChunk, check_cloud_file, rgb_to_uint16


def _open(path: Path):
    import pye57  # lazily: only E57 needs it

    check_cloud_file(path)
    try:
        return pye57.E57(str(path))
    except Exception as err:  # noqa: BLE001 - libE57Format raises its own exception types
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InputError(path, f"not a readable E57 file ({msg})") from None


def _scan(path: Path, e57, i: int) -> PointChunk:
    try:
        d = e57.read_scan(i, intensity=True, colors=True, ignore_missing_fields=True, transform=True)
    except Exception as err:  # noqa: BLE001 - libE57Format raises its own exception types
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        raise InputError(path, f"scan {i}: unreadable ({msg})") from None
    xyz = np.column_stack([d["cartesianX"], d["cartesianY"], d["cartesianZ"]]).astype(np.float64)
    chunk = PointChunk(xyz=xyz)
    if all(k in d for k in ("colorRed", "colorGreen", "colorBlue")):
        rgb = np.column_stack([d["colorRed"], d["colorGreen"], d["colorBlue"]]).astype(np.int64)
        chunk.rgb = rgb_to_uint16(rgb, eight_bit=rgb.max(initial=0) <= 255)
    if "intensity" in d:
        val = np.asarray(d["intensity"])
        if val.dtype.kind == "f":
            chunk.extra["intensity"] = val.astype(np.float32)
        else:
            chunk.intensity = val.astype(np.uint16)
    return chunk


def iter_e57(path: Path, chunk_points: int) -> Iterator[PointChunk]:
    """The points of every scan of an E57 file, in chunks of at most ``chunk_points``."""
    from storage.formats.point_chunk import check_finite_points

    e57 = _open(path)
    try:
        if e57.scan_count == 0:
            raise InputError(path, "the E57 file holds no scans")
        for i in range(e57.scan_count):
            whole = _scan(path, e57, i)
            check_finite_points(path, whole.xyz)
            for lo in range(0, len(whole), chunk_points):
                yield whole.take(slice(lo, lo + chunk_points))
    finally:
        e57.close()


__all__ = ["iter_e57"]
