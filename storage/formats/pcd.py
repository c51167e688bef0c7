"""PCD point clouds (through open3d, read whole; registered in :mod:`storage.formats.points`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.point_chunk import PointChunk, check_cloud_file, rgb_to_uint16


def read_pcd(path: Path) -> PointChunk:
    import open3d as o3d  # lazily: only PCD needs it

    check_cloud_file(path)
    try:
        pcd = o3d.t.io.read_point_cloud(str(path))
    except Exception as err:
        raise InputError(path, f"unreadable PCD file ({err})") from err
    attrs = pcd.point
    if "positions" not in attrs or len(attrs["positions"]) == 0:
        raise InputError(path, "no points (or an unreadable PCD file)")
    chunk = PointChunk(xyz=attrs["positions"].numpy().astype(np.float64))
    if "colors" in attrs:
        colors = attrs["colors"].numpy()
        chunk.rgb = rgb_to_uint16(colors, eight_bit=colors.dtype == np.uint8)
    if "intensity" in attrs:
        val = attrs["intensity"].numpy().reshape(len(chunk.xyz), -1)[:, 0]
        if val.dtype.kind == "f":
            chunk.extra["intensity"] = val
        else:
            chunk.intensity = val.astype(np.uint16)
    return chunk


__all__ = ["read_pcd"]
