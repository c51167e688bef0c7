"""The partition stage's I/O: a tile's staging runs -> its Parquet patch store (Liu et al. 2023, §3.2.1).

Unit: a tile, fingerprinted by the names and fingerprints of the staging files that feed it
(:func:`storage.contracts.staging.staging_fingerprint`), so it is redone exactly when that set changes. A tile with
no data left loses its store; a tile blocked by a bad input keeps its last good store marked stale
(``stale.json``), which no later stage and no campus-wide statistic reads until the tile succeeds again.
The pure partition is in :mod:`tasks.partition.kernels`, the bounded-memory merge in
:mod:`tasks.partition.stream`.
"""

from __future__ import annotations

import contextlib
import os
import socket
import time
from pathlib import Path

import numpy as np

from storage.atomic import write_json_atomic
from storage.contracts.columns import RunReader
from storage.contracts.staging import is_point_run, staged_files, staging_fingerprint
from storage.errors import EmptyTileError, InputError
from storage.frame import CampusFrame
from storage.ids import TileId
from storage.patches.schema import (
    FACES_FILE,
    PATCHES_FILE,
    POINTS_FILE,
    SIDE_TABLES,
    TileMeta,
    side_table_path,
)
from storage.patches.write import write_tile_tables
from storage.workdir.layout import STALE_FILE, WorkDir
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.partition.kernels import SideSummary, merge_runs, patches_table, summarise_side
from tasks.units import Done, run_unit


def staged_pieces(parts: list[Path]) -> tuple[dict[str, list[dict]], list[str]]:
    """A tile's staging runs (sorted paths) as {"points": [columns per run], "faces": [...]} and the
    tile's texture list, texture indices of each mesh run shifted into it."""
    pieces: dict[str, list[dict]] = {"points": [], "faces": []}
    textures: list[str] = []
    for p in parts:
        reader = RunReader(p)
        cols = reader.read()
        if is_point_run(p):
            pieces["points"].append(cols)
        else:
            base = len(textures)
            textures += reader.meta.get("textures", [])
            cols["texture"] = np.where(cols["texture"] >= 0, cols["texture"] + base, -1).astype(np.int16)
            pieces["faces"].append(cols)
    return pieces, textures


def remove_store(tile_dir: Path) -> None:
    """Remove a tile's store: the 'done' marker first, so a crash half-way leaves no readable tile."""
    for name in (PATCHES_FILE, POINTS_FILE, FACES_FILE, STALE_FILE,
                 *(f"{t}.parquet" for t in SIDE_TABLES)):
        (tile_dir / name).unlink(missing_ok=True)
    with contextlib.suppress(OSError):
        tile_dir.rmdir()


def mark_stale(tile_dir: Path, error: str) -> None:
    """Keep a tile's last good store but exclude it from every later stage until it succeeds again."""
    if (tile_dir / PATCHES_FILE).exists():
        with contextlib.suppress(OSError):
            write_json_atomic(tile_dir / STALE_FILE, {"error": error, "since": time.time()})


def write_tile_store(parts: list[Path], tile_dir: Path, meta: TileMeta, budget_bytes: int,
                     force_stream: bool = False) -> dict:
    """Partition a tile's staging runs into its store: in memory when the estimate fits the budget left
    above this process's current RSS, else by the k-way merge of ``tasks.partition.stream`` (same files).
    Runs merge in the order of their content digests (:func:`storage.contracts.columns.content_digest`), not of their
    names (which carry the inputs' source ids): the same inputs under other names or URLs give the same
    store, rows of one patch in the same order."""
    from tasks.partition.stream import IN_MEMORY_BYTES, STREAM_BYTES, stream_partition_tile

    info = {p: (r.content, r.n_rows) for p, r in ((p, RunReader(p)) for p in parts)}
    parts = sorted(parts, key=lambda p: (info[p][0], p.name))  # content order: names do not matter
    point_runs = [p for p in parts if is_point_run(p)]
    face_runs = [p for p in parts if not is_point_run(p)]
    rows_p, rows_f = (sum(info[p][1] for p in runs) for runs in (point_runs, face_runs))
    free = budget_bytes - current_rss_bytes()
    need = rows_p * IN_MEMORY_BYTES["points"] + rows_f * IN_MEMORY_BYTES["faces"]
    if need <= free and not force_stream:
        n_patches = _write_in_memory(parts, tile_dir, meta)
        return {"n_points": rows_p, "n_faces": rows_f, "n_patches": n_patches, "streamed": False}
    budget_rows = max(int(free // max(STREAM_BYTES["points"], STREAM_BYTES["faces"])), 10_000)
    out = stream_partition_tile(point_runs, face_runs, tile_dir, meta, budget_rows)
    return out | {"streamed": True}


def _write_in_memory(parts: list[Path], tile_dir: Path, meta: TileMeta) -> int:
    """Merge a tile's runs in memory and write its three tables; returns the number of patches."""
    pieces, textures = staged_pieces(parts)
    sides = {}
    for side, faces in (("points", False), ("faces", True)):
        if pieces[side]:
            cols, part = merge_runs(pieces[side])
            sides[side] = (cols, summarise_side(cols, part, faces))
        pieces[side] = None  # free the runs as soon as they are merged
    empty = SideSummary.empty()
    patches = patches_table(sides.get("points", (None, empty))[1], sides.get("faces", (None, empty))[1])
    meta = TileMeta(meta.tile, meta.patch_size_m, meta.crs, tuple(textures))
    write_tile_tables(tile_dir, sides.get("points", (None,))[0], sides.get("faces", (None,))[0], patches, meta)
    return len(patches["patch"])


def current_rss_bytes() -> int:
    """This process's resident set size now, bytes (Linux /proc; 0 when unknown)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def run_partition_tile(tile: TileId, cfg: CampusConfig, wd: WorkDir, frame: CampusFrame,
                       blocked: str | None = None, force_stream: bool = False) -> dict:
    """Partition one tile's staged points and faces into its patch store.

    ``blocked``: the error of an input this tile depends on; the tile then fails with it (its last good
    store is kept, marked stale). Returns the unit summary (status done / empty / failed).
    """
    tile_dir = wd.tile_dir(tile)
    parts = staged_files(wd, tile.key)
    fp = combine_fingerprints(staging_fingerprint(parts) + [blocked or ""])
    params = cfg.stage_params("partition") | {"frame": frame.to_json()}

    def work() -> Done:
        t0 = time.perf_counter()
        if blocked:
            raise InputError(None, blocked)
        if not parts:
            remove_store(tile_dir)  # a tile that lost its data
            raise EmptyTileError(None, f"tile {tile.key} holds no points and no faces")
        for name in SIDE_TABLES:  # side tables describe the old patches: never join them to new ones
            side_table_path(tile_dir, name).unlink(missing_ok=True)
        meta = TileMeta(tile=tile.key, patch_size_m=tuple(cfg.partition.patch_size_m), crs=frame.crs)
        budget = cfg.partition.memory_budget_mb * 2**20
        counts = write_tile_store(parts, tile_dir, meta, budget, force_stream=force_stream)
        (tile_dir / STALE_FILE).unlink(missing_ok=True)
        summary = {"tile": tile.key, **counts, "n_inputs": len(parts),
                   "worker": f"{socket.gethostname()}:{os.getpid()}",
                   "partition_seconds": time.perf_counter() - t0}
        return Done(outputs=[str((tile_dir / PATCHES_FILE).relative_to(wd.root))], summary=summary)

    return run_unit(wd, "partition", tile.key, fp, params, work,
                    on_fail=lambda: mark_stale(tile_dir, blocked or "partition failed"))
