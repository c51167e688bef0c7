"""XYZ / TXT / CSV point clouds: numeric columns, read whole in blocks of lines (registered in
:mod:`storage.formats.points`)."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.point_chunk import PointChunk, check_cloud_file, rgb_to_uint16


def read_xyz(path: Path, block_lines: int = 1_000_000) -> PointChunk:
    """Columns ``x y z [r g b] [intensity]`` (whitespace, comma or semicolon separated; '#' comments;
    one non-numeric header line allowed). RGB columns all within 0..255 are read as 8-bit and scaled to
    16-bit; other column counts keep the columns beyond x y z in ``extra['col3']``, ``extra['col4']``..."""
    check_cloud_file(path)
    with open(path, "r", errors="replace") as f:
        first = ""
        for first in f:
            if first.strip() and not first.lstrip().startswith("#"):
                break
        delimiter = "," if "," in first else (";" if ";" in first else None)
        try:
            [float(t) for t in first.replace(",", " ").replace(";", " ").split()]
            skip = 0
        except ValueError:
            skip = 1
        f.seek(0)
        blocks, line_no = [], 0
        lines = (ln for ln in f if ln.strip() and not ln.lstrip().startswith("#"))
        for _ in range(skip):
            next(lines, None)
        while block := list(itertools.islice(lines, block_lines)):
            try:
                blocks.append(np.loadtxt(block, delimiter=delimiter, ndmin=2, dtype=np.float64))
            except ValueError as err:
                rows = f"{line_no + 1}..{line_no + len(block)}"
                raise InputError(path, f"malformed row among data rows {rows}: {err}") from err
            line_no += len(block)
    if not blocks:
        raise InputError(path, "no points (no data rows)")
    table = np.concatenate(blocks)
    if table.shape[1] < 3:
        raise InputError(path, f"expected at least 3 columns (x y z), found {table.shape[1]}")
    chunk = PointChunk(xyz=np.ascontiguousarray(table[:, :3]))
    ncol = table.shape[1]
    if ncol in (6, 7):
        rgb = table[:, 3:6]
        finite = rgb[np.isfinite(rgb)]
        chunk.rgb = rgb_to_uint16(rgb.astype(np.int64), eight_bit=finite.size == 0 or finite.max() <= 255)
    if ncol in (4, 7):
        chunk.intensity = np.clip(table[:, -1], 0, 65535).astype(np.uint16)
    if ncol not in (3, 4, 6, 7):
        chunk.extra = {f"col{i}": table[:, i].copy() for i in range(3, ncol)}
    return chunk


__all__ = ["read_xyz"]
