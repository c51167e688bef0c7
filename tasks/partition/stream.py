"""Partition a tile within a memory budget, whatever the tile holds: a k-way merge of sorted runs.

Ingest writes every tile's rows as *sorted runs* (``staging/{tile}/{unit}.parquet``, sorted by patch key,
row groups of 32 k rows with min/max key statistics). A tile whose rows would not fit the budget in
memory is merged here block by block: a block is a range of patch keys ``[lo, hi)`` chosen from the
row-group statistics so that the row groups it touches fit the budget; its rows are read from every
run (only the row groups overlapping the range), stably sorted by key, and appended to the store's
tables, whose row groups are written as they complete (``storage.patches.TableWriter``). A block
never splits a patch (its bounds are keys), and the result is the same file, byte for byte, as the
in-memory path (``tasks.partition.stage.write_tile_store``: ``merge_runs`` + ``write_tile_tables``): rows of one patch keep
the order run by run, and the row groups fall at the same rows.

Memory: one block (at most the budget's rows, plus up to one row group per run when a single step of
the plan exceeds it) and the per-patch summaries (a few dozen bytes per patch).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.contracts.columns import RunReader
from storage.patches.schema import FACES_FILE, PATCHES_FILE, POINTS_FILE, TileMeta
from storage.patches.write import TableWriter, complete_columns, write_patches_table
from tasks.partition.kernels import SideSummary, merge_runs, patches_table, summarise_side

KEY_MAX = np.iinfo(np.int64).max
# Bytes of memory per row while partitioning (measured: benchmarks/partition_bench.py --big-tile):
IN_MEMORY_BYTES = {"points": 350, "faces": 900}  # the whole tile loaded, sorted, gathered, written
STREAM_BYTES = {"points": 250, "faces": 600}  # one block of the merge


@dataclass
class Run:
    """One staging run (``storage.contracts.columns.RunReader``: batch key statistics (g, 3) [min, max, rows]) and
    the offset of its texture indices in the tile's texture list (faces)."""

    reader: RunReader
    texture_base: int = 0

    @property
    def groups(self) -> np.ndarray:
        return self.reader.groups

    @property
    def n_rows(self) -> int:
        return self.reader.n_rows


def open_runs(paths: list[Path]) -> tuple[list[Run], list[str]]:
    """Open sorted runs (in the given order); returns them and the concatenated texture list."""
    runs, textures = [], []
    for p in paths:
        reader = RunReader(p)
        runs.append(Run(reader, len(textures)))
        textures += reader.meta.get("textures", [])
    return runs, textures


def plan_blocks(groups: list[np.ndarray], budget_rows: int) -> list[tuple[int, int]]:
    """Key ranges [lo, hi) covering every row, each touching row groups of at most ``budget_rows`` rows
    in total (or one step of the plan when a single step exceeds it).

    groups: per run, (g, 3) int64 [min key, max key, rows] of its row groups (keys ascending per run).
    Cut points are row-group minimum keys, so a block boundary never splits a patch.

    >>> g = [np.array([[0, 9, 10], [10, 19, 10]]), np.array([[0, 19, 10]])]
    >>> plan_blocks(g, 25)
    [(0, 10), (10, 9223372036854775807)]
    """
    allg = np.concatenate([g for g in groups if len(g)]) if any(len(g) for g in groups) else np.zeros((0, 3), np.int64)
    if len(allg) == 0:
        return []
    cuts = np.unique(allg[:, 0])
    blocks, lo = [], int(cuts[0])
    while True:
        live = allg[allg[:, 1] >= lo]  # row groups not yet wholly behind
        order = np.argsort(live[:, 0], kind="stable")
        mins, cum = live[order, 0], np.cumsum(live[order, 2])
        cand = cuts[cuts > lo]
        if len(cand) == 0:
            blocks.append((lo, int(KEY_MAX)))
            return blocks
        cost = np.concatenate(([0], cum))[np.searchsorted(mins, cand, side="left")]  # rows touched by [lo, c)
        if cum[-1] <= budget_rows:  # everything left fits
            blocks.append((lo, int(KEY_MAX)))
            return blocks
        ok = np.flatnonzero(cost <= budget_rows)
        hi = int(cand[ok[-1]]) if len(ok) else int(cand[0])
        blocks.append((lo, hi))
        lo = hi


def read_range(run: Run, lo: int, hi: int) -> dict[str, np.ndarray] | None:
    """The rows of ``run`` with lo <= patch < hi (a contiguous slice of the sorted run), reading only
    the record batches that overlap the range; None when there are none."""
    g = np.flatnonzero((run.groups[:, 1] >= lo) & (run.groups[:, 0] < hi))
    if len(g) == 0:
        return None
    cols = run.reader.read(g.tolist())
    keys = cols["patch"]
    a, b = np.searchsorted(keys, lo, side="left"), np.searchsorted(keys, hi, side="left")
    if a == b:
        return None
    return {k: v[a:b] for k, v in cols.items()}


def stream_side(runs: list[Run], table: str, out: Path, meta: TileMeta, budget_rows: int) -> SideSummary:
    """Merge the runs of one side (table "points" or "faces") into the store file ``out``."""
    n_rows = sum(r.n_rows for r in runs)
    parts: list[SideSummary] = []
    with TableWriter(out, table, meta.to_json(table, n_rows)) as writer:
        for lo, hi in plan_blocks([r.groups for r in runs], budget_rows):
            pieces = []
            for r in runs:
                cols = read_range(r, lo, hi)
                if cols is None:
                    continue
                if table == "faces" and r.texture_base:
                    cols["texture"] = np.where(cols["texture"] >= 0, cols["texture"] + r.texture_base, -1).astype(np.int16)
                pieces.append(cols)
            if not pieces:
                continue
            block, part = merge_runs(pieces)
            del pieces
            block = complete_columns(block, table, out)
            parts.append(summarise_side(block, part, faces=table == "faces"))
            writer.write(block)
            del block
    return SideSummary.concat(parts)


def stream_partition_tile(point_runs: list[Path], face_runs: list[Path], tile_dir: Path, meta: TileMeta,
                          budget_rows: int) -> dict:
    """Partition a tile from its sorted runs into its store within ``budget_rows`` rows per block.

    point_runs / face_runs: the tile's staging runs, in the order the in-memory path concatenates them.
    meta: the tile's TileMeta (its ``textures`` are replaced by the runs' concatenated list).
    Returns {"n_points", "n_faces", "n_patches", "blocks"}.
    """
    pruns, _ = open_runs(point_runs)
    fruns, textures = open_runs(face_runs)
    meta = TileMeta(meta.tile, meta.patch_size_m, meta.crs, tuple(textures))
    tile_dir.mkdir(parents=True, exist_ok=True)
    (tile_dir / PATCHES_FILE).unlink(missing_ok=True)  # the 'done' marker goes first and comes back last
    p_side = stream_side(pruns, "points", tile_dir / POINTS_FILE, meta, budget_rows)
    f_side = stream_side(fruns, "faces", tile_dir / FACES_FILE, meta, budget_rows)
    patches = patches_table(p_side, f_side)
    n_points, n_faces = int(p_side.counts.sum()), int(f_side.counts.sum())
    write_patches_table(tile_dir, patches, meta, n_points, n_faces)
    return {"n_points": n_points, "n_faces": n_faces, "n_patches": len(patches["patch"]),
            "blocks": len(plan_blocks([r.groups for r in pruns], budget_rows))
            + len(plan_blocks([r.groups for r in fruns], budget_rows))}
