"""The work-dir layout of DESIGN.md, and campus.json.

::

    campus.json                     CRS, origin, registration, inputs, config snapshot, code version
    registration.json               the recorded MLS -> mesh similarity (reused by registration.mode pinned)
    manifest.parquet                one row per (stage, unit), consolidated by the flow
    manifest.d/{stage}/{unit}.json  the same rows, one file each, written atomically by the tasks
    scan/{source}.npz               per mesh file: surface samples registration aligns to
    staging/{tile}/{unit}-{k}.parquet  ingest output: rows of one input unit routed to one tile
    tiles/{ix}_{iy}/points.parquet  MLS points of the tile, sorted by patch
    tiles/{ix}_{iy}/faces.parquet   mesh faces of the tile, sorted by patch
    tiles/{ix}_{iy}/patches.parquet one row per patch (its presence marks a complete store)
    tiles/{ix}_{iy}/{labels,outliers,grades}.parquet  side tables, one row per patch
    tiles/{ix}_{iy}/stale.json      the store is the last good one; its inputs now fail (see the error)
    report/                         figures for the run report (histograms, ...)
    export/lod/{node}.npz           the export's decimated mesh per tileset node (its cache)
    output/                         what a user opens: tileset.json, georef.json, overview.glb, content/, points/,
                                    report.html
    prefect/                        the embedded Prefect server's database (run history)

Tile keys are world-anchored (``tasks.config.CampusConfig.grid``): tile (ix, iy) covers
``[ix*t, (ix+1)*t) x [iy*t, (iy+1)*t)`` world metres.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage import __version__, recorded
from storage.atomic import read_json, write_json_atomic
from storage.errors import InputError
from storage.frame import CampusFrame
from storage.ids import TileId

CAMPUS_SCHEMA_VERSION = 2
STALE_FILE = "stale.json"


class _Under:
    """A fixed path under a work dir's root, read as an attribute:
    ``WorkDir(r).tileset_json == r / "output/tileset.json"``."""

    def __init__(self, rel: str):
        self.rel = rel

    def __get__(self, wd, owner=None):
        return self if wd is None else wd.root / self.rel


@dataclass(frozen=True)
class WorkDir:
    root: Path

    def __init__(self, root: str | Path):
        object.__setattr__(self, "root", Path(root).absolute())

    # the fixed paths of the layout (module doc), each a read-only attribute: ``wd.tileset_json``
    campus_json = _Under("campus.json")
    manifest = _Under("manifest.parquet")
    manifest_dir = _Under("manifest.d")
    report_dir = _Under("report")
    prefect_dir = _Under("prefect")
    output_dir = _Under("output")  # what a user opens: the 3D Tiles, their georeference and the run report
    tileset_json = _Under("output/tileset.json")
    georef_json = _Under("output/georef.json")
    tileset_3tz = _Under("output/tileset.3tz")  # the output packed as one 3D Tiles archive (export.archive: 3tz)
    report_html = _Under("output/report.html")
    lod_cache_dir = _Under("export/lod")  # the export's decimated mesh per tileset node

    def tile_dir(self, tile: TileId) -> Path:
        return self.root / "tiles" / tile.key

    def staging_dir(self, tile: TileId) -> Path:
        return self.root / "staging" / tile.key

    # the listings below count a work dir on a bucket's recorded files that are not downloaded (storage.recorded)
    def staged_tiles(self) -> list[TileId]:
        return sorted(TileId.from_key(p.name) for p in recorded.children(self.root / "staging") if recorded.is_dir(p))

    def done_tiles(self) -> list[TileId]:
        """Tiles with a complete store (live or stale)."""
        return sorted(TileId.from_key(p.name) for p in recorded.children(self.root / "tiles")
                      if recorded.is_file(p / "patches.parquet"))

    def live_tiles(self) -> list[TileId]:
        """Tiles with a complete store that is current (not marked stale): what later stages read."""
        return [t for t in self.done_tiles() if not recorded.is_file(self.tile_dir(t) / STALE_FILE)]

    def stale_tiles(self) -> list[TileId]:
        return [t for t in self.done_tiles() if recorded.is_file(self.tile_dir(t) / STALE_FILE)]

    def tile_keys_on_disk(self) -> list[str]:
        """Every tile folder, complete or not (to drop stores the current plan no longer names)."""
        return sorted(p.name for p in recorded.children(self.root / "tiles") if recorded.is_dir(p))


def write_campus(wd: WorkDir, frame: CampusFrame, registration: dict, config_snapshot: dict,
                 extra: dict | None = None) -> None:
    """Write campus.json atomically. registration: {"matrix": 4x4 list, "scale", "fitness", ...}."""
    doc = {
        "schema_version": CAMPUS_SCHEMA_VERSION,
        "frame": frame.to_json(),
        "registration": registration,
        "config": config_snapshot,
        "code_version": __version__,
    }
    doc.update(extra or {})
    write_json_atomic(wd.campus_json, doc)


def read_campus(wd: WorkDir) -> dict:
    path = wd.campus_json
    doc = read_json(path, "no campus.json: run the register stage first (ms3d run CONFIG)")
    if doc.get("schema_version") != CAMPUS_SCHEMA_VERSION:
        raise InputError(path, f"campus.json schema_version {doc.get('schema_version')}, this ms3d reads "
                               f"{CAMPUS_SCHEMA_VERSION}: re-run `ms3d run` to rebuild the work dir")
    return doc


def campus_frame(doc: dict) -> CampusFrame:
    return CampusFrame.from_json(doc["frame"])


def registration_matrix(doc: dict) -> np.ndarray:
    """(4, 4) float64 similarity mapping MLS world coordinates (minus origin) to campus-local."""
    return np.asarray(doc["registration"]["matrix"], dtype=np.float64)
