"""The regions plan on disk: ``regions/regions.json``, one :class:`Region` record per connected set of bad
patches to rebuild, read by the repair (one unit per region) and the merge (which regions reach a tile).

::

    {"schema_version": 1,
     "grades": {tile key: "grades" | "labels" | "all" | "none"},   where each tile's grades came from
     "tile_fingerprints": {tile key: storage.patches.state.store_fingerprint},
     "grid": storage.grid.PatchGrid.to_json(),
     "regions": [Region.to_json(), ...]}                              sorted by key

The folder of a region is ``regions/{key}/`` (its files: :mod:`storage.contracts.region_mesh`); folders whose name
starts with ``_`` are caches (``_occupancy``), never regions.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.atomic import write_json_atomic
from storage.grid import PatchGrid

REGIONS_DIR = "regions"
PLAN_FILE = "regions.json"
REGION_SCHEMA_VERSION = 1
OCCUPANCY_DIR = "_occupancy"


@dataclass(frozen=True)
class Region:
    """One connected set of patches to rebuild.

    key: stable id ("r" + hex of the smallest rebuilt patch key), the folder ``regions/{key}/``.
    number: stable 31-bit number for per-face provenance. patches: (n,) int64 sorted keys of the
    rebuilt set (bad patches + growth); bad: (b,) int64 the bad patches among them; context: (c,) int64
    the ring of existing patches read for stitching and fusion context (never rebuilt).
    tiles: tile keys holding any patch of patches or context. parent: key of the region this one was
    split from ("" if not split). est_bytes: estimated working set, bytes.
    """

    key: str
    number: int
    patches: np.ndarray = field(repr=False)
    bad: np.ndarray = field(repr=False)
    context: np.ndarray = field(repr=False)
    tiles: tuple[str, ...] = ()
    parent: str = ""
    est_bytes: int = 0

    @property
    def n_patches(self) -> int:
        return len(self.patches)

    def to_json(self) -> dict:
        return {"key": self.key, "number": self.number, "patches": self.patches.tolist(),
                "bad": self.bad.tolist(), "context": self.context.tolist(), "tiles": list(self.tiles),
                "parent": self.parent, "est_bytes": int(self.est_bytes)}

    @classmethod
    def from_json(cls, d: dict) -> Region:
        arr = lambda k: np.asarray(d[k], np.int64)
        return cls(d["key"], int(d["number"]), arr("patches"), arr("bad"), arr("context"), tuple(d["tiles"]),
                   d.get("parent", ""), int(d.get("est_bytes", 0)))


def plan_path(root: str | Path) -> Path:
    """``regions/regions.json`` of the work dir at ``root``."""
    return Path(root) / REGIONS_DIR / PLAN_FILE


def region_dir(root: str | Path, key: str) -> Path:
    """``regions/{key}/`` of the work dir at ``root``."""
    return Path(root) / REGIONS_DIR / key


def write_plan(root: str | Path, regions: list[Region], grades: dict[str, str], tile_fingerprints: dict[str, str],
               grid: PatchGrid) -> None:
    """Write the plan atomically (format: module docstring)."""
    doc = {"schema_version": REGION_SCHEMA_VERSION, "grades": grades, "tile_fingerprints": tile_fingerprints,
           "grid": grid.to_json(), "regions": [r.to_json() for r in regions]}
    write_json_atomic(plan_path(root), doc, indent=None)


def read_plan_doc(root: str | Path) -> dict | None:
    """The plan document as written, or None when no plan was written."""
    p = plan_path(root)
    return json.loads(p.read_text()) if p.exists() else None


def read_plan(root: str | Path) -> list[Region]:
    """The regions of the last plan, [] when none was written."""
    doc = read_plan_doc(root)
    return [] if doc is None else [Region.from_json(d) for d in doc["regions"]]


def plan_grid(doc: dict) -> PatchGrid:
    """The patch grid a plan document was made on."""
    g = doc["grid"]
    return PatchGrid(tuple(g["size_m"]), g["tile_size_m"], tuple(g["anchor_m"]))



def occupancy_path(root: str | Path, tile_key: str) -> Path:
    """``regions/_occupancy/{tile}.npz``: the cached MLS-occupied voxels of a tile (texture occluders)."""
    return Path(root) / REGIONS_DIR / OCCUPANCY_DIR / f"{tile_key}.npz"
