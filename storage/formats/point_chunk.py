"""The values every point-cloud reader returns: ``PointChunk`` (a block of points) and ``CloudInfo``
(what a file holds), plus the input checks all readers share.

Coordinates are float64 WORLD metres in the file's CRS.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.errors import InputError


@dataclass
class PointChunk:
    """A block of points. All arrays have the same length n.

    xyz: (n, 3) float64, metres, WORLD frame (the file's CRS).
    rgb: (n, 3) uint16 (LAS convention, 0..65535) or None.
    intensity: (n,) uint16 or None.
    gps_time: (n,) float64 seconds (as stored) or None.
    classification: (n,) uint8 (ASPRS classes) or None.
    extra: other named per-point arrays, each (n,) or (n, k).
    """

    xyz: np.ndarray
    rgb: np.ndarray | None = None
    intensity: np.ndarray | None = None
    gps_time: np.ndarray | None = None
    classification: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.xyz)

    def take(self, index) -> PointChunk:
        """The points selected by ``index`` (a slice, boolean mask or integer array)."""
        pick = lambda a: None if a is None else a[index]
        return PointChunk(
            xyz=self.xyz[index],
            rgb=pick(self.rgb),
            intensity=pick(self.intensity),
            gps_time=pick(self.gps_time),
            classification=pick(self.classification),
            extra={k: v[index] for k, v in self.extra.items()},
        )

    @staticmethod
    def concat(chunks: Iterable[PointChunk]) -> PointChunk:
        """One chunk holding all points of ``chunks`` in order; an optional field survives only if
        every chunk has it."""
        chunks = list(chunks)
        if not chunks:
            return PointChunk(xyz=np.zeros((0, 3)))

        def cat(name):
            parts = [getattr(c, name) for c in chunks]
            return None if any(p is None for p in parts) else np.concatenate(parts)

        keys = set.intersection(*(set(c.extra) for c in chunks))
        return PointChunk(
            xyz=np.concatenate([c.xyz for c in chunks]),
            rgb=cat("rgb"),
            intensity=cat("intensity"),
            gps_time=cat("gps_time"),
            classification=cat("classification"),
            extra={k: np.concatenate([c.extra[k] for c in chunks]) for k in sorted(keys)},
        )


@dataclass(frozen=True)
class CloudInfo:
    """What a point-cloud file holds, read without loading it (LAS/LAZ) or with one streamed pass.

    bounds: (2, 3) float64 [min, max] world metres. scale/offset: LAS quantisation (None otherwise).
    crs: "EPSG:nnnn" when pyproj finds a code, another pyproj string when it does not, None if absent.
    """

    path: str
    format: str
    point_count: int
    bounds: np.ndarray = field(compare=False)
    crs: str | None = None
    scale: tuple[float, float, float] | None = None
    offset: tuple[float, float, float] | None = None
    has_rgb: bool = False
    has_time: bool = False
    point_format: int | None = None
    version: str | None = None


def check_cloud_file(path: Path) -> None:
    """InputError unless ``path`` is an existing, non-empty file."""
    if not path.exists():
        raise InputError(path, "file not found")
    if path.is_dir():
        raise InputError(path, "is a folder, expected a point-cloud file")
    if path.stat().st_size == 0:
        raise InputError(path, "empty file (0 bytes)")


def check_finite_points(path: Path, xyz: np.ndarray) -> None:
    """InputError counting the rows of ``xyz`` ((n, 3)) with a NaN or infinite coordinate."""
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        raise InputError(path, f"{int(bad.sum()):,} of {len(xyz):,} points have NaN or infinite coordinates")


def crs_to_string(crs) -> str | None:
    """pyproj CRS -> "EPSG:nnnn" when pyproj can identify a code, else its own string; None -> None."""
    if crs is None:
        return None
    epsg = crs.to_epsg()
    return f"EPSG:{epsg}" if epsg is not None else crs.to_string()


def rgb_to_uint16(rgb: np.ndarray, eight_bit: bool) -> np.ndarray:
    if rgb.dtype.kind == "f":
        return np.clip(np.round(rgb * 65535.0), 0, 65535).astype(np.uint16)
    if eight_bit:
        return rgb.astype(np.uint16) * 257  # 255 -> 65535
    return np.clip(rgb, 0, 65535).astype(np.uint16)

__all__ = ["rgb_to_uint16", "CloudInfo", "PointChunk", "check_cloud_file", "check_finite_points", "crs_to_string"]
