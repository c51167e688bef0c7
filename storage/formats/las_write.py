"""LAS 1.4 / LAZ writer: :class:`LasChunkWriter` (chunk by chunk, atomic) and :func:`write_points`; re-exported
by :mod:`storage.formats.las`, whose readers are the other half.

Coordinates are float64 WORLD metres (LAS integers times scale plus offset).
"""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path
from typing import Self

import laspy
import numpy as np

from storage.atomic import atomic_path
from storage.formats.point_chunk import PointChunk

LAS_INT32_MAX = 2**31 - 1


def choose_offset(xyz: np.ndarray, snap_m: float = 1000.0) -> np.ndarray:
    """A LAS offset near the data: the bounding-box centre snapped to ``snap_m``. (3,) float64.

    At 1 mm scale an int32 reaches +-2147 km from the offset, so any campus fits.
    """
    if len(xyz) == 0:
        return np.zeros(3)
    centre = (xyz.min(axis=0) + xyz.max(axis=0)) / 2.0
    return np.round(centre / snap_m) * snap_m


class LasChunkWriter:
    """Write a LAS 1.4 (``.las``) or LAZ (``.laz``, lazrs) file chunk by chunk, atomically.

    Memory is bounded by the largest chunk. The file appears at ``path`` only when the context exits
    without error (written under a temporary name beside it, then renamed).

    Args:
        path: output ``.las`` / ``.laz``.
        crs: e.g. "EPSG:32650" (anything pyproj accepts), written as a WKT VLR; None writes no CRS.
        scale: (3,) metres per integer step; 1 mm by default.
        offset: (3,) world metres; None chooses one near the first chunk (``choose_offset``).
        point_format: 6 (no colour), 7 (RGB, default) or 8 (RGB + NIR); all carry GPS time.
        extra_dims: {name: numpy dtype} written as LAS extra bytes from ``PointChunk.extra[name]``.

    Example::

        with LasChunkWriter("out.laz", crs="EPSG:32650") as w:
            for chunk in iter_points("in.las"):
                w.write(chunk)
    """

    def __init__(
        self,
        path: str | Path,
        crs: str | None = None,
        scale=(0.001, 0.001, 0.001),
        offset=None,
        point_format: int = 7,
        extra_dims: dict[str, object] | None = None,
    ):
        self.path = Path(path)
        if self.path.suffix.lower() not in (".las", ".laz"):
            raise ValueError(f"{self.path}: LasChunkWriter writes .las or .laz, not {self.path.suffix!r}")
        if point_format not in (6, 7, 8):
            raise ValueError(f"point_format must be 6, 7 or 8 (LAS 1.4), got {point_format}")
        self.header = laspy.LasHeader(point_format=point_format, version="1.4")
        self.header.scales = np.asarray(scale, dtype=np.float64)
        self.extra_dims = {k: np.dtype(v) for k, v in (extra_dims or {}).items()}
        if self.extra_dims:
            params = [laspy.ExtraBytesParams(name=k, type=v) for k, v in self.extra_dims.items()]
            self.header.add_extra_dims(params)
        if crs is not None:
            import pyproj

            self.header.add_crs(pyproj.CRS.from_user_input(crs))
        self._offset = None if offset is None else np.asarray(offset, dtype=np.float64)
        self._stack: contextlib.ExitStack | None = None
        self._writer = None
        self.points_written = 0

    def __enter__(self) -> Self:
        self._stack = contextlib.ExitStack()
        self._tmp = self._stack.enter_context(atomic_path(self.path))
        return self

    def write(self, chunk: PointChunk) -> None:
        """Append the points of ``chunk`` (xyz float64 world metres)."""
        if self._stack is None:
            raise RuntimeError("use LasChunkWriter as a context manager")
        xyz = np.asarray(chunk.xyz, dtype=np.float64)
        bad = ~np.isfinite(xyz).all(axis=1)
        if bad.any():
            raise ValueError(f"{self.path}: refusing to write {int(bad.sum())} NaN/inf points")
        if len(xyz) == 0:  # an empty first chunk must not fix the offset
            return
        if self._writer is None:
            self._open(xyz)
        self._writer.write_points(self._record(chunk, xyz))
        self.points_written += len(xyz)

    def _open(self, xyz: np.ndarray) -> None:
        self.header.offsets = self._offset if self._offset is not None else choose_offset(xyz)
        self._writer = laspy.open(
            self._tmp, mode="w", header=self.header, do_compress=self.path.suffix.lower() == ".laz"
        )

    def _record(self, chunk: PointChunk, xyz: np.ndarray):
        h = self._writer.header
        ints = np.round((xyz - h.offsets) / h.scales)
        if np.abs(ints).max() > LAS_INT32_MAX:
            raise ValueError(
                f"{self.path}: coordinates {xyz.min(axis=0)}..{xyz.max(axis=0)} do not fit LAS int32 at scale "
                f"{list(h.scales)} around offset {list(h.offsets)}; pass an offset nearer the data"
            )
        rec = laspy.ScaleAwarePointRecord.zeros(len(xyz), header=h)
        for i, name in enumerate("XYZ"):
            rec[name] = ints[:, i].astype(np.int32)
        if chunk.intensity is not None:
            rec["intensity"] = chunk.intensity
        if chunk.classification is not None:
            rec["classification"] = chunk.classification
        if chunk.gps_time is not None:
            rec["gps_time"] = chunk.gps_time
        if chunk.rgb is not None and h.point_format.id in (7, 8):
            for i, name in enumerate(("red", "green", "blue")):
                rec[name] = chunk.rgb[:, i]
        for name in self.extra_dims:
            if name not in chunk.extra:
                raise ValueError(f"{self.path}: chunk has no extra field {name!r} declared in extra_dims")
            rec[name] = chunk.extra[name]
        return rec

    def _abandon(self) -> None:
        if self._writer is not None:
            with contextlib.suppress(Exception):
                self._writer.close()

    def __exit__(self, exc_type, exc, tb):
        stack, self._stack = self._stack, None
        if exc_type is not None:
            self._abandon()
            return stack.__exit__(exc_type, exc, tb)
        try:
            if self._writer is None:  # nothing written: an empty but valid file
                self._open(np.zeros((0, 3)))
            self._writer.close()
        except BaseException:
            self._abandon()
            if not stack.__exit__(*sys.exc_info()):
                raise
            return False
        return stack.__exit__(None, None, None)


def write_points(path: str | Path, chunk: PointChunk, crs: str | None = None, **writer_kwargs) -> Path:
    """Write one PointChunk to a LAS/LAZ file atomically (see LasChunkWriter for the options)."""
    with LasChunkWriter(path, crs=crs, **writer_kwargs) as writer:
        writer.write(chunk)
    return Path(path)


__all__ = ["LAS_INT32_MAX", "LasChunkWriter", "choose_offset", "write_points"]
