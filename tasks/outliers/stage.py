"""The outliers stage's I/O (Liu et al. 2023, §3.2.2): the campus-wide fit of points and faces per patch
over every live tile, each tile's ``outliers.parquet`` rewritten only where its flags change, and both
histograms saved as PNG. The robust fit itself is :mod:`tasks.outliers.fit`.
"""

from __future__ import annotations

import json
import time

import numpy as np

from storage.errors import InputError
from storage.patches.read import PatchTable, read_side_table
from storage.patches.schema import side_table_path
from storage.patches.state import store_fingerprint
from storage.patches.write import write_side_table
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.outliers.fit import fit_count_outliers, save_histogram_png
from tasks.units import Done, run_unit


def run_outliers(cfg: CampusConfig, wd: WorkDir) -> dict:
    """Fit the campus-wide distributions of faces and points per patch (normal fit on log counts) over
    every live (done, not stale) tile, write each tile's ``outliers.parquet`` where its flags changed,
    and save both histograms as PNG. Records nothing: :func:`run_outliers_unit` is the resumable unit."""
    t0 = time.perf_counter()
    tiles = wd.live_tiles()
    stores = [(t, PatchTable(wd.tile_dir(t))) for t in tiles]  # the patches tables only, never points or faces
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
    return out


def outliers_fingerprint(wd: WorkDir) -> str:
    """What the outlier fit reads: the patch tables of every live tile (the store files' sizes and mtimes,
    not the side tables it writes itself)."""
    return combine_fingerprints(["outliers", *(f"{t.key}:{store_fingerprint(wd.tile_dir(t))}" for t in wd.live_tiles())])


def outliers_outputs(wd: WorkDir) -> list[str]:
    """The outlier fit's files (work-dir relative) that exist: each live tile's ``outliers`` side table and
    the two histograms."""
    paths = [side_table_path(wd.tile_dir(t), "outliers") for t in wd.live_tiles()]
    paths += [wd.report_dir / f"patch_{n}_histogram.png" for n in ("points", "faces")]
    return [str(p.relative_to(wd.root)) for p in paths if p.exists()]


def run_outliers_unit(cfg: CampusConfig, wd: WorkDir) -> dict:
    """The campus-wide fit as one resumable unit ("outliers", "campus"): skipped while no live store and
    neither the ``partition`` outlier / minimum-count fields changed; its summary."""
    def work() -> Done:
        return Done(outputs=outliers_outputs(wd), summary=json.loads(json.dumps(run_outliers(cfg, wd))))

    return run_unit(wd, "outliers", "campus", outliers_fingerprint(wd), cfg.stage_params("outliers"), work)
