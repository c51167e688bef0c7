"""The labels stage's I/O: each tile's ``labels.parquet`` (1 bad, 0 good per patch) from a synth
``defects.json`` or a CSV of world-anchored patch ids (``inputs.labels``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import file_sha256
from storage.ids import TileId
from storage.inputs.location import is_url
from storage.inputs.remote import local_input
from storage.patches.read import PatchStore
from storage.patches.schema import PATCHES_FILE, side_table_path
from storage.patches.write import write_side_table
from storage.workdir.labels import bad_keys_from_csv, bad_keys_from_defects
from storage.workdir.layout import STALE_FILE, WorkDir
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.units import Done, run_unit


def bad_patch_keys(labels_path: str, cfg: CampusConfig) -> np.ndarray:
    """(b,) int64 sorted keys of the patches a synth defects.json or a label CSV marks bad."""
    p = Path(labels_path)
    if p.suffix.lower() == ".csv":
        return bad_keys_from_csv(p)
    return bad_keys_from_defects(p, cfg.grid())


def run_labels_tile(tile: TileId, cfg: CampusConfig, wd: WorkDir) -> dict | None:
    """Write the tile's ``labels.parquet`` (1 bad, 0 good) when a labels file is configured; without one,
    remove a stale labels table. Returns the unit summary, or None when there is nothing to do."""
    tile_dir = wd.tile_dir(tile)
    if not cfg.inputs.labels:
        recorded.unlink(side_table_path(tile_dir, "labels"))
        return None
    store = recorded.state(tile_dir / PATCHES_FILE)  # on a bucket: what the records say, nothing downloaded
    if store is None or recorded.is_file(tile_dir / STALE_FILE):
        return None
    labels = Path(cfg.inputs.labels) if not is_url(cfg.inputs.labels) else cfg.inputs.labels  # identity
    try:
        labels_fp = file_sha256(local_input(str(labels)) if is_url(labels) else labels)
    except OSError as e:
        return {"unit": tile.key, "status": "failed", "error": f"{labels}: cannot read the labels file ({e.strerror})"}
    fp = combine_fingerprints([labels_fp, str(labels), f"{store.mtime_ns}"])

    def work() -> Done:
        store = PatchStore(tile_dir)
        keys = store.patches()["patch"]
        bad = bad_patch_keys(local_input(str(labels)), cfg)
        lab = np.isin(keys, bad).astype(np.int8)
        write_side_table(tile_dir, "labels", {"patch": keys, "label": lab}, store.meta, labels_file=str(labels))
        return Done(outputs=[str(side_table_path(tile_dir, "labels").relative_to(wd.root))],
                    summary={"n_bad": int(lab.sum()), "n_labelled": len(lab)})

    return run_unit(wd, "labels", tile.key, fp, cfg.stage_params("labels"), work)
