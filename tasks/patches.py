"""The partition stage per tile (staging -> Parquet patch store, labels) and the global patch
outlier stage (§3.2.2).

The pure partition lives in ``tasks.partition`` and the outlier fit in ``tasks.outliers``; this
module reads and writes the work dir.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from pathlib import Path

import numpy as np

from storage.atomic import file_fingerprint
from storage.columns import read_columns
from storage.errors import EmptyTileError, InputError
from storage.ids import TileId
from storage.manifest import ManifestRecord, combine_fingerprints, is_done, params_hash, write_record
from storage.workdir import WorkDir, read_campus
from tasks.config import CampusConfig
from tasks.partition import build_tile_tables

log = logging.getLogger("ms3d.patches")


def _concat(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray] | None:
    if not parts:
        return None
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def load_staged_tile(parts: list[Path]) -> tuple[dict | None, dict | None, list[str]]:
    """A tile's staging files (sorted paths) as column dicts: (points, faces, textures), texture
    indices of each mesh file shifted into the tile's concatenated texture list."""
    pts_parts, face_parts, textures = [], [], []
    for p in parts:
        cols, meta = read_columns(p)
        if p.name.startswith("points-"):
            pts_parts.append(cols)
        else:
            base = len(textures)
            textures += meta.get("textures", [])
            cols["texture"] = np.where(cols["texture"] >= 0, cols["texture"] + base, -1).astype(np.int16)
            face_parts.append(cols)
    return _concat(pts_parts), _concat(face_parts), textures


def bad_patch_keys(labels_path: str, origin: np.ndarray, patch_size) -> np.ndarray:
    """Packed keys of bad patches from a synth defects.json or a CSV of patch ids. (k,) int64 sorted."""
    from storage.labels import bad_keys_from_csv, bad_keys_from_defects

    p = Path(labels_path)
    if p.suffix.lower() == ".csv":
        return np.unique(bad_keys_from_csv(p))
    return np.unique(bad_keys_from_defects(p, np.asarray(origin, np.float64), patch_size))


def partition_params(cfg: CampusConfig, campus: dict) -> dict:
    return cfg.stage_params("partition") | {"labels": cfg.inputs.labels, "frame": campus["frame"]}


def run_partition_tile(tile: TileId, cfg: CampusConfig, wd: WorkDir, blocked: str | None = None) -> dict:
    """Partition one tile's staged points and faces into its patch store.

    ``blocked``: the error of an input this tile depends on; the tile then fails with it.
    Raises InputError (tile failed) or returns a summary; an empty tile is recorded as ``empty``.
    """
    from storage.patch_store import TileMeta, write_tile_tables

    campus = read_campus(wd)
    staging = wd.staging_dir(tile)
    parts = sorted(staging.glob("*.parquet")) if staging.exists() else []
    fp = combine_fingerprints([f"{p.name}:{file_fingerprint(p)}" for p in parts] + [blocked or ""])
    ph = params_hash(partition_params(cfg, campus))
    done = is_done(wd, "partition", tile.key, fp, ph)
    if done is not None:
        return done.summary | {"skipped": True}
    t0 = time.perf_counter()
    if blocked:
        err = InputError(None, f"tile {tile.key}: {blocked}")
        write_record(wd, ManifestRecord("partition", tile.key, "failed", fp, ph, error=str(err)))
        raise err
    try:
        points, faces, textures = load_staged_tile(parts)
        if points is None and faces is None:
            raise EmptyTileError(staging, f"tile {tile.key} holds no points and no faces")
        pts_s, faces_s, patches = build_tile_tables(points, faces, cfg.partition.patch_size_m)
        if cfg.inputs.labels:
            bad = bad_patch_keys(cfg.inputs.labels, campus["frame"]["origin"], cfg.partition.patch_size_m)
            patches["label"] = np.isin(patches["patch"], bad).astype(np.int8)
        meta = TileMeta(tile=tile.key, patch_size_m=tuple(cfg.partition.patch_size_m),
                        crs=campus["frame"].get("crs"), textures=tuple(textures))
        write_tile_tables(wd.tile_dir(tile), pts_s or None, faces_s or None, patches, meta)
    except EmptyTileError as e:
        (wd.tile_dir(tile) / "patches.parquet").unlink(missing_ok=True)  # a tile that lost its data
        write_record(wd, ManifestRecord("partition", tile.key, "empty", fp, ph, error=str(e),
                                        seconds=time.perf_counter() - t0))
        return {"tile": tile.key, "status": "empty"}
    except InputError as e:
        write_record(wd, ManifestRecord("partition", tile.key, "failed", fp, ph, error=str(e),
                                        seconds=time.perf_counter() - t0))
        raise
    n_pts = len(pts_s.get("x", [])) if pts_s else 0
    n_faces = len(faces_s.get("x0", [])) if faces_s else 0
    summary = {"tile": tile.key, "status": "done", "n_points": n_pts, "n_faces": n_faces,
               "n_patches": len(patches["patch"]),
               "n_bad": int((patches["label"] == 1).sum()), "n_labelled": int((patches["label"] >= 0).sum()),
               "worker": f"{socket.gethostname()}:{os.getpid()}"}
    outputs = [str((wd.tile_dir(tile) / f).relative_to(wd.root)) for f in ("patches.parquet",)]
    write_record(wd, ManifestRecord("partition", tile.key, "done", fp, ph, seconds=time.perf_counter() - t0,
                                    outputs=outputs, summary=summary))
    return summary


def run_outliers(cfg: CampusConfig, wd: WorkDir) -> dict:
    """Fit the campus-wide distributions of faces and points per patch (normal fit on log counts),
    flag the patches outside the band in every tile's patches table, save both histograms as PNG."""
    from storage.patch_store import PatchStore, update_patch_columns
    from tasks.outliers import fit_count_outliers, save_histogram_png

    t0 = time.perf_counter()
    tiles = wd.done_tiles()
    tables = [(t, PatchStore(wd.tile_dir(t)).patches()) for t in tiles]
    if not tables:
        return {"n_patches": 0}
    n_pts = np.concatenate([tb["n_points"] for _, tb in tables])
    n_faces = np.concatenate([tb["n_faces"] for _, tb in tables])
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
    at = 0
    for t, tb in tables:
        n = len(tb["n_points"])
        fp_, ff = fits["points"][1][at:at + n], fits["faces"][1][at:at + n]
        missing = (tb["n_points"] < cfg.partition.min_points) | (tb["n_faces"] < cfg.partition.min_faces)
        update_patch_columns(wd.tile_dir(t), {"outlier_points": fp_, "outlier_faces": ff, "outlier": fp_ | ff | missing})
        at += n
    out = {"n_patches": len(n_pts), "seconds": time.perf_counter() - t0}
    for name, (fit, flags) in fits.items():
        out[name] = {"mean_log10": float(fit.mean), "std_log10": float(fit.std), "low": float(fit.low),
                     "high": float(fit.high), "flagged": int(flags.sum())}
    write_record(wd, ManifestRecord("outliers", "campus", "done", seconds=out["seconds"], summary=out))
    return out
