"""Planning a nightly rerun: how long deciding what is done takes for a campus of many regions.

Builds a synthetic work dir in a temporary folder: ``--tiles`` tile stores (empty table files: a store's
identity is sizes and mtimes, :func:`storage.patches.state.store_fingerprint`), a region plan of
``--regions`` regions of a few patches each over one or two tiles, and a done record with its outputs for
every region, exactly as :func:`tasks.repair.run_region` records them. Then it times

1. the planner (:func:`tasks.repair.pending_regions`: one read of the plan and of the records) on the
   unchanged campus: every region must be skipped;
2. the planner after one tile's store changed (a strip rewritten): exactly the regions on that tile run;
3. the per-unit path the flow took before (``run_region`` on each key, skipping through its own record
   check), on a sample of ``--sample`` keys, extrapolated to all of them;
4. the flow's planner for a per-tile stage (``flows.planned.pending``: the stage's task function called
   under ``tasks.units.planning``) over the ``--tiles`` stores, each with a done record fingerprinted by
   its store (as classify does; the stage's own setup, e.g. loading the network, is not included).

Usage: ``python benchmarks/rerun_bench.py [--regions 50000] [--tiles 400] [--sample 200]``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flows.planned import pending
from storage.contracts.region_plan import REGION_SCHEMA_VERSION, Region, plan_path, region_dir
from storage.patches.schema import FACES_FILE, PATCHES_FILE, POINTS_FILE
from storage.patches.state import store_fingerprint
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import ManifestRecord
from tasks.config import CampusConfig
from tasks.repair import pending_regions, region_fingerprint, run_region
from tasks.repair.stage import region_params
from tasks.units import Done, run_unit, unit_params


def build_work_dir(root: Path, n_regions: int, n_tiles: int, seed: int = 0) -> tuple[CampusConfig, list[str]]:
    """A work dir with ``n_tiles`` stores, a plan of ``n_regions`` regions and a done record for each.
    Returns (config, region keys in plan order)."""
    rng = np.random.default_rng(seed)
    cfg = CampusConfig(name="bench", work_dir=str(root))
    cfg.repair.texture.enabled = False
    wd = WorkDir(root)
    side = int(np.ceil(np.sqrt(n_tiles)))
    tiles = [f"{i % side}_{i // side}" for i in range(n_tiles)]
    for t in tiles:
        d = root / "tiles" / t
        d.mkdir(parents=True)
        for name in (PATCHES_FILE, POINTS_FILE, FACES_FILE):
            (d / name).write_bytes(b"x" * 16)
    regions = []
    for i in range(n_regions):
        first = int(rng.integers(n_tiles))
        tl = (tiles[first],) if rng.random() < 0.8 else (tiles[first], tiles[(first + 1) % n_tiles])
        patches = np.sort(rng.choice(1 << 40, 6, replace=False)).astype(np.int64) + (i << 41)
        regions.append(Region(f"r{i:012x}", i, patches, patches[:3], patches[:0], tl, "", 1 << 20))
    plan_path(root).parent.mkdir(parents=True, exist_ok=True)
    plan_path(root).write_text(json.dumps({"schema_version": REGION_SCHEMA_VERSION, "grades": {},
                                           "tile_fingerprints": {}, "grid": cfg.grid().to_json(),
                                           "regions": [r.to_json() for r in regions]}))
    ph, memo = unit_params("region", region_params(cfg)), {}
    rec_dir = wd.manifest_dir / "region"
    rec_dir.mkdir(parents=True)
    for r in regions:  # what run_region records for a kept region (region.json only), written directly
        d = region_dir(root, r.key)
        d.mkdir(parents=True)
        (d / "region.json").write_text("{}")
        rec = ManifestRecord("region", r.key, "done", region_fingerprint(r, wd, cfg, memo), ph, seconds=1.0,
                             outputs=[f"regions/{r.key}/region.json"],
                             summary={"region": r.key, "result": "kept", "unit": r.key, "status": "done"},
                             updated_at=time.time())
        (rec_dir / f"{r.key}.json").write_text(json.dumps(rec.__dict__))
    return cfg, [r.key for r in regions]


class _TileStage:
    """A per-tile task as the flow maps it (``fn(batch, cfg_json)``): each tile is a ``run_unit`` of the
    "classify" stage fingerprinted by its store."""

    def __init__(self, wd: WorkDir):
        self.wd = wd

    def fn(self, batch: list[str], cfg_json: dict) -> list[dict]:
        return [run_unit(self.wd, "classify", k, store_fingerprint(self.wd.root / "tiles" / k), cfg_json,
                         lambda: Done(outputs=[f"tiles/{k}/{PATCHES_FILE}"])) for k in batch]


def time_tile_stage(wd: WorkDir, tiles: list[str]) -> tuple[float, float]:
    """(seconds of the first run recording every tile, seconds of the no-op plan) for :class:`_TileStage`."""
    stage, params = _TileStage(wd), {"model_hash": "bench"}
    t0 = time.perf_counter()
    ran = stage.fn(tiles, params)
    t_run = time.perf_counter() - t0
    assert not any(r["skipped"] for r in ran)
    t0 = time.perf_counter()
    todo, done = pending(wd, stage, tiles, "bench tiles", cfg_json=params)
    t_plan = time.perf_counter() - t0
    assert not todo and len(done) == len(tiles)
    return t_run, t_plan


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--regions", type=int, default=50_000)
    ap.add_argument("--tiles", type=int, default=400)
    ap.add_argument("--sample", type=int, default=200, help="keys timed through the per-unit path")
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="ms3d-rerun-") as tmp:
        root = Path(tmp)
        t0 = time.perf_counter()
        cfg, keys = build_work_dir(root, a.regions, a.tiles)
        wd = WorkDir(root)
        print(f"built {a.regions:,} regions over {a.tiles} tiles with done records in {time.perf_counter() - t0:.1f} s")

        t0, c0 = time.perf_counter(), time.process_time()
        todo, skipped = pending_regions(keys, cfg, wd)
        t_plan, c_plan = time.perf_counter() - t0, time.process_time() - c0
        assert not todo and len(skipped) == len(keys), (len(todo), len(skipped))
        print(f"no-op plan:        {t_plan:6.2f} s wall, {c_plan:.2f} s CPU ({len(todo)} to run, {len(skipped):,} "
              f"skipped; {1e6 * t_plan / len(keys):.0f} us per unit)")

        changed = "0_0"
        p = root / "tiles" / changed / PATCHES_FILE
        p.write_bytes(b"y" * 17)
        os.utime(p)
        expect = {k for k, r in zip(keys, json.loads(plan_path(root).read_text())["regions"]) if changed in r["tiles"]}
        t0 = time.perf_counter()
        todo, skipped = pending_regions(keys, cfg, wd)
        t_plan2 = time.perf_counter() - t0
        assert set(todo) == expect, (len(todo), len(expect))
        print(f"one tile changed:  {t_plan2:6.2f} s  ({len(todo)} to run = the regions on tile {changed}, "
              f"{len(skipped):,} skipped)")

        sample = [k for k in keys if k not in expect][: a.sample]
        t0 = time.perf_counter()
        res = [run_region(k, cfg, wd) for k in sample]
        t_old = time.perf_counter() - t0
        assert all(r["skipped"] for r in res)
        per = t_old / len(sample)
        print(f"per-unit skipping (before): {1e3 * per:.1f} ms per unit on {len(sample)} units "
              f"-> {per * len(keys):,.0f} s for {len(keys):,} (task-run overhead not included)")

        tiles = sorted(p.name for p in (root / "tiles").iterdir())
        t_run, t_tiles = time_tile_stage(wd, tiles)
        print(f"per-tile stage no-op plan: {t_tiles:6.2f} s for {len(tiles)} tiles "
              f"({1e3 * t_tiles / len(tiles):.2f} ms per tile, no task run; recording them took {t_run:.2f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
