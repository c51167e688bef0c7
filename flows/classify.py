"""The classify stage's Prefect task (the campus flow maps it over batches of tiles after partition).

Wiring in ``flows/campus.py`` (done by whoever owns that file)::

    from flows.classify import classify_task
    ...
    grades = ex.map(classify_task, tile_batches, "classify", cfg_json=cfg_json).results()
    for s in grades:
        if s["status"] == "failed":
            failed[f"classify {s['unit']}"] = s["error"]
    drop_unplanned_records(wd, "classify", set(tiles))

(after ``outliers``; pass ``stages={..., "classify": grades}`` to ``summarise``). The network is loaded
once per worker process (``tasks.classify.stage.load_model`` caches it).
"""

from __future__ import annotations

from prefect import task
from prefect.cache_policies import NONE as NO_CACHE


@task(name="classify", cache_policy=NO_CACHE)
def classify_task(tile_keys: list[str], cfg_json: dict) -> list[dict]:
    """Grade the pairs of a batch of tiles; one summary per tile that has a live store."""
    from storage.ids import TileId
    from storage.workdir import WorkDir
    from tasks.classify.stage import run_classify_tile
    from tasks.config import CampusConfig

    cfg = CampusConfig.model_validate(cfg_json)
    wd = WorkDir(cfg.work_dir)
    out = []
    for k in tile_keys:
        res = run_classify_tile(TileId.from_key(k), cfg, wd)
        if res is not None:
            out.append(res)
    return out
