"""The points overlay's reading and writing (:mod:`tasks.export.points` makes its content from arrays): the tile
stores' points, thinned, coloured by their patches' grades, one glb per tile under ``output/points/`` with its
``tileset.json``, rewritten only when a store, its grades, the georeference or the budget changed. A tile's glb
is one :class:`PointsJob`, run here or mapped over a cluster beside the export's nodes."""

from __future__ import annotations

import hashlib
import json
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import read_json, write_bytes_atomic, write_json_atomic
from storage.patches.read import PatchStore, PatchTable
from storage.patches.schema import PATCHES_FILE, POINTS_FILE
from storage.patches.state import patch_grades, store_fingerprint
from tasks.export.content import box_from_bounds
from tasks.export.georef import EnuProjector, GeoRef, enu_to_gltf
from tasks.export.points import (
    POINTS_BUDGET,
    POINTS_VERSION,
    build_points_glb,
    point_status,
    points_tileset_json,
    thin_indices,
)


def _digest(parts: list[str]) -> str:
    return hashlib.sha256("|".join(parts).encode()).hexdigest()[:32]


def _tile_points(tile_dir: Path, keep: int, seed: int, grades_mode: str) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (k, 3) float32 campus-local, status (k,) int8) of a seeded subset of a tile's points, coloured by
    the grades repair acted on (``repair.grades``: :func:`storage.patches.state.patch_grades`). Columns are
    read one at a time, so memory is one column of the tile plus the subset."""
    store = PatchStore(tile_dir)
    p = store.patches()
    _, grade, _ = patch_grades(store, grades_mode)
    idx = thin_indices(store.n_points, keep, seed)
    xyz = np.empty((len(idx), 3), np.float32)
    for j, c in enumerate("xyz"):
        xyz[:, j] = store.read_all_stacked("points", [c], np.float32)[idx, 0]
    return xyz, point_status(p["point_stop"], grade, p["n_faces"], idx)


@dataclass(frozen=True)
class PointsJob:
    """One tile of the points overlay (picklable: mapped over a cluster beside the nodes): its store, how many
    points to keep, the seed of their choice, the grades they are coloured by, and the folder of its glb."""

    tile: str
    tile_dir: Path
    out: Path  # work_dir/output/points
    keep: int
    seed: int
    grades_mode: str
    georef: GeoRef


def build_points(job: PointsJob) -> dict:
    """Write ``job.out/{tile}.glb``; returns {"tile", "box": its ENU box, "points": points kept}."""
    xyz, status = _tile_points(job.tile_dir, job.keep, job.seed, job.grades_mode)
    enu = EnuProjector(job.georef).local_to_enu(xyz)
    write_bytes_atomic(job.out / f"{job.tile}.glb", build_points_glb(enu_to_gltf(enu), status))
    return {"tile": job.tile, "box": box_from_bounds(enu.min(axis=0), enu.max(axis=0)), "points": len(xyz)}


def write_points_overlay(tiles_dir: Path, out_dir: Path, tiles: list[str], georef: GeoRef,
                         budget: int = POINTS_BUDGET, seed: int = 0, grades_mode: str = "auto",
                         run: Callable[[list[PointsJob]], list[dict]] | None = None) -> dict:
    """Write (or keep, when unchanged) ``out_dir/tileset.json`` and ``out_dir/{key}.glb`` from the stores of
    ``tiles`` under ``tiles_dir`` (see :mod:`tasks.export.points`). run: a callable that runs
    :func:`build_points` on every job (in order), e.g. mapped with the nodes; default: here, one after the other.
    Returns {"tiles", "points", "written", "tileset"}."""
    with_points = [k for k in tiles if recorded.is_file(tiles_dir / k / PATCHES_FILE)
                   and recorded.is_file(tiles_dir / k / POINTS_FILE)]
    counts = {k: int(PatchTable(tiles_dir / k).patches()["n_points"].sum()) for k in with_points}
    counts = {k: n for k, n in counts.items() if n}
    if not counts:
        recorded.remove_tree(out_dir)
        return {"tiles": 0, "points": 0, "written": False, "tileset": None}
    fp = _digest([str(POINTS_VERSION), str(budget), str(seed), grades_mode, json.dumps(georef.to_json(), sort_keys=True)]
                              + [f"{k}:{store_fingerprint(tiles_dir / k, sides=('grades', 'labels'))}" for k in sorted(counts)])
    state = out_dir / "fingerprints.json"
    old = read_json(state, "no points overlay state") if state.exists() else {}
    if old.get("fingerprint") == fp and (out_dir / "tileset.json").exists():
        return {"tiles": len(counts), "points": old["points"], "written": False, "tileset": str(out_dir / "tileset.json")}
    total = sum(counts.values())
    jobs = [PointsJob(k, tiles_dir / k, out_dir, max(1, round(budget * counts[k] / total)) if total > budget
                      else counts[k], seed + zlib.crc32(k.encode()), grades_mode, georef) for k in sorted(counts)]
    done = run(jobs) if run is not None else [build_points(j) for j in jobs]
    boxes, kept = {d["tile"]: d["box"] for d in done}, sum(d["points"] for d in done)
    for stale in recorded.glob(out_dir, "*.glb"):
        if stale.stem not in boxes:
            recorded.unlink(stale)
    write_json_atomic(out_dir / "tileset.json", points_tileset_json(boxes, georef.tileset_transform()))
    write_json_atomic(state, {"fingerprint": fp, "points": kept, "tiles": sorted(boxes)})
    return {"tiles": len(boxes), "points": kept, "written": True, "tileset": str(out_dir / "tileset.json")}


__all__ = ["PointsJob", "build_points", "write_points_overlay"]
