"""The per-tile stages after ingest: partition (staging -> Parquet patch store), labels, and the
campus-wide patch outlier stage (§3.2.2).

The pure partition lives in ``tasks.partition.kernels`` and the outlier fit in ``tasks.outliers.fit``; this module
reads and writes the work dir.

- **partition** (unit: a tile): fingerprinted by the names and fingerprints of the staging files that
  feed it, so it is redone exactly when that set changes. A tile with no data left loses its store; a
  tile blocked by a bad input keeps its last good store marked stale (``stale.json``), which no later
  stage and no campus-wide statistic reads until the tile succeeds again.
- **labels** (unit: a tile): ``labels.parquet`` from a synth ``defects.json`` or a CSV of world-anchored
  patch ids, fingerprinted by the labels file's content (editing it in place relabels).
- **outliers** (unit: the campus): the normal fit of log counts over every live tile; a tile's
  ``outliers.parquet`` is rewritten only when its flags change.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import socket
import time
from pathlib import Path

import numpy as np

from storage.atomic import file_sha256, write_json_atomic
from storage.columns import RunReader
from storage.errors import EmptyTileError, InputError
from storage.frame import CampusFrame
from storage.ids import TileId
from storage.manifest import ManifestRecord, combine_fingerprints, write_record
from storage.patch_store import (
    FACES_FILE,
    PATCHES_FILE,
    POINTS_FILE,
    SIDE_TABLES,
    PatchStore,
    TileMeta,
    read_side_table,
    side_table_path,
    write_side_table,
    write_tile_tables,
)
from storage.workdir import STALE_FILE, WorkDir
from tasks.config import CampusConfig
from tasks.ingest.stage import staged_files, staging_fingerprint
from tasks.partition.kernels import SideSummary
from tasks.units import Done, run_unit

log = logging.getLogger("ms3d.patches")


def staged_pieces(parts: list[Path]) -> tuple[dict[str, list[dict]], list[str]]:
    """A tile's staging runs (sorted paths) as {"points": [columns per run], "faces": [...]} and the
    tile's texture list, texture indices of each mesh run shifted into it."""
    pieces: dict[str, list[dict]] = {"points": [], "faces": []}
    textures: list[str] = []
    for p in parts:
        reader = RunReader(p)
        cols = reader.read()
        if p.name.startswith("p"):
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


# ----------------------------------------------------------------------------------- partition


def write_tile_store(parts: list[Path], tile_dir: Path, meta: TileMeta, cfg: CampusConfig, frame: CampusFrame,
                     budget_bytes: int, force_stream: bool = False) -> dict:
    """Partition a tile's staging runs into its store: in memory when the estimate fits the budget left
    above this process's current RSS, else by the k-way merge of ``tasks.partition.stream`` (same files)."""
    from tasks.partition.stream import IN_MEMORY_BYTES, STREAM_BYTES, stream_partition_tile

    point_runs = [p for p in parts if p.name.startswith("p")]
    face_runs = [p for p in parts if p.name.startswith("m")]
    rows_p, rows_f = (sum(RunReader(p).n_rows for p in runs) for runs in (point_runs, face_runs))
    free = budget_bytes - current_rss_bytes()
    need = rows_p * IN_MEMORY_BYTES["points"] + rows_f * IN_MEMORY_BYTES["faces"]
    if need <= free and not force_stream:
        from storage.patch_store import write_tile_tables as write
        from tasks.partition.kernels import merge_runs, patches_table, summarise_side

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
        write(tile_dir, sides.get("points", (None,))[0], sides.get("faces", (None,))[0], patches, meta)
        return {"n_points": rows_p, "n_faces": rows_f, "n_patches": len(patches["patch"]), "streamed": False}
    budget_rows = max(int(free // max(STREAM_BYTES["points"], STREAM_BYTES["faces"])), 10_000)
    out = stream_partition_tile(point_runs, face_runs, tile_dir, meta, budget_rows)
    return out | {"streamed": True}


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
        counts = write_tile_store(parts, tile_dir, meta, cfg, frame, budget, force_stream=force_stream)
        (tile_dir / STALE_FILE).unlink(missing_ok=True)
        summary = {"tile": tile.key, **counts, "n_inputs": len(parts),
                   "worker": f"{socket.gethostname()}:{os.getpid()}",
                   "partition_seconds": time.perf_counter() - t0}
        return Done(outputs=[str((tile_dir / PATCHES_FILE).relative_to(wd.root))], summary=summary)

    return run_unit(wd, "partition", tile.key, fp, params, work,
                    on_fail=lambda: mark_stale(tile_dir, blocked or "partition failed"))


# ----------------------------------------------------------------------------------- labels


def bad_patch_keys(labels_path: str, cfg: CampusConfig) -> np.ndarray:
    """(b,) int64 sorted keys of the patches a synth defects.json or a label CSV marks bad."""
    from storage.labels import bad_keys_from_csv, bad_keys_from_defects

    p = Path(labels_path)
    if p.suffix.lower() == ".csv":
        return bad_keys_from_csv(p)
    return bad_keys_from_defects(p, cfg.grid())


def run_labels_tile(tile: TileId, cfg: CampusConfig, wd: WorkDir) -> dict | None:
    """Write the tile's ``labels.parquet`` (1 bad, 0 good) when a labels file is configured; without one,
    remove a stale labels table. Returns the unit summary, or None when there is nothing to do."""
    tile_dir = wd.tile_dir(tile)
    if not cfg.inputs.labels:
        side_table_path(tile_dir, "labels").unlink(missing_ok=True)
        return None
    if not (tile_dir / PATCHES_FILE).exists() or (tile_dir / STALE_FILE).exists():
        return None
    labels = Path(cfg.inputs.labels)
    try:
        labels_fp = file_sha256(labels)
    except OSError as e:
        return {"unit": tile.key, "status": "failed", "error": f"{labels}: cannot read the labels file ({e.strerror})"}
    fp = combine_fingerprints([labels_fp, str(labels), f"{(tile_dir / PATCHES_FILE).stat().st_mtime_ns}"])

    def work() -> Done:
        store = PatchStore(tile_dir)
        keys = store.patches()["patch"]
        bad = bad_patch_keys(str(labels), cfg)
        lab = np.isin(keys, bad).astype(np.int8)
        write_side_table(tile_dir, "labels", {"patch": keys, "label": lab}, store.meta, labels_file=str(labels))
        return Done(outputs=[str(side_table_path(tile_dir, "labels").relative_to(wd.root))],
                    summary={"n_bad": int(lab.sum()), "n_labelled": len(lab)})

    return run_unit(wd, "labels", tile.key, fp, cfg.stage_params("labels"), work)


# ----------------------------------------------------------------------------------- outliers


def run_outliers(cfg: CampusConfig, wd: WorkDir) -> dict:
    """Fit the campus-wide distributions of faces and points per patch (normal fit on log counts) over
    every live (done, not stale) tile, write each tile's ``outliers.parquet`` where its flags changed,
    and save both histograms as PNG."""
    from tasks.outliers.fit import fit_count_outliers, save_histogram_png

    t0 = time.perf_counter()
    tiles = wd.live_tiles()
    stores = [(t, PatchStore(wd.tile_dir(t))) for t in tiles]
    if not stores:
        return {"n_patches": 0, "tiles_rewritten": 0}
    tables = [(t, s, s.patches()) for t, s in stores]
    n_pts = np.concatenate([tb["n_points"] for _, _, tb in tables])
    n_faces = np.concatenate([tb["n_faces"] for _, _, tb in tables])
    lo, hi = cfg.partition.outlier_sigma_low, cfg.partition.outlier_sigma_high
    fits = {}
    for name, counts in (("points", n_pts), ("faces", n_faces)):
        nz = counts > 0
        fit = fit_count_outliers(counts[nz], lo, hi)
        flags = np.zeros(len(counts), bool)
        flags[nz] = fit.mask
        fits[name] = (fit, flags)
        save_histogram_png(counts[nz], fit, wd.report_dir / f"patch_{name}_histogram.png",
                           title=f"{name} per patch (n={int(nz.sum())}, flagged {int(fit.mask.sum())})")
    at, rewritten = 0, 0
    for t, store, tb in tables:
        n = len(tb["n_points"])
        fp_, ff = fits["points"][1][at:at + n], fits["faces"][1][at:at + n]
        missing = (tb["n_points"] < cfg.partition.min_points) | (tb["n_faces"] < cfg.partition.min_faces)
        cols = {"patch": tb["patch"], "outlier_points": fp_, "outlier_faces": ff, "outlier": fp_ | ff | missing}
        at += n
        try:
            old = read_side_table(wd.tile_dir(t), "outliers", tb["patch"])
        except InputError:
            old = None
        if old is not None and all(np.array_equal(old[0][c], v) for c, v in cols.items()):
            continue
        write_side_table(wd.tile_dir(t), "outliers", cols, store.meta)
        rewritten += 1
    out = {"n_patches": len(n_pts), "tiles": len(tables), "tiles_rewritten": rewritten,
           "seconds": time.perf_counter() - t0}
    for name, (fit, flags) in fits.items():
        out[name] = {"mean_log10": float(fit.mean), "std_log10": float(fit.std), "low": float(fit.low),
                     "high": float(fit.high), "flagged": int(flags.sum())}
    write_record(wd, ManifestRecord("outliers", "campus", "done", seconds=out["seconds"],
                                    summary=json.loads(json.dumps(out))))
    return out
