"""The export stage in the flow: 3D Tiles of every merged tile, recorded in the manifest like the other
stages (``tasks.export.build.run_export`` rebuilds only the nodes whose content changed)."""

from __future__ import annotations

import time

from storage.errors import InputError
from storage.manifest import ManifestRecord, write_record
from storage.workdir import WorkDir
from tasks.units import os_error_message, peak_rss_mb, reset_peak_rss


def run_export_stage(cfg, wd: WorkDir, map_jobs=None) -> dict:
    """Export when any tile has a merged mesh; returns the unit summary (status done / empty / failed).

    map_jobs: see ``tasks.export.build.run_export`` (the flow maps the quadtree's nodes over its workers)."""
    from tasks.export.build import run_export

    if not any((wd.root / "tiles").glob("*/merged.json")):
        return {"unit": "campus", "status": "empty", "skipped": False}
    t0, c0 = time.perf_counter(), time.process_time()
    reset_peak_rss()
    try:
        out = run_export(wd.root, cfg.export, workers=1, map_jobs=map_jobs)  # no pool: a Dask worker may not fork
    except (InputError, OSError) as e:
        msg = str(e) if isinstance(e, InputError) else os_error_message(e)
        write_record(wd, ManifestRecord("export", "tileset", "failed", error=msg, seconds=time.perf_counter() - t0))
        return {"unit": "campus", "status": "failed", "error": f"export: {msg}", "skipped": False}
    summary = {k: v for k, v in out.items() if isinstance(v, (int, float, str, bool))}
    summary |= {"stage_wall_seconds": round(time.perf_counter() - t0, 3), "peak_rss_mb": peak_rss_mb(),
                "cpu_seconds": round(time.process_time() - c0, 3), "nodes_built": len(out["built"])}
    if map_jobs is None:  # built here: this record carries the work
        seconds = time.perf_counter() - t0
    else:  # each node recorded its own seconds where it was built; this is the planning and the tileset
        seconds = summary["cpu_seconds"]
        from storage.housekeeping import drop_unplanned_records

        drop_unplanned_records(wd, "export", set(out["built"]) | set(out["reused"]) | {"tileset", "L-1_0_0"})
    write_record(wd, ManifestRecord("export", "tileset", "done", seconds=seconds, outputs=["output/tileset.json"],
                                    summary=summary))
    return {"unit": "tileset", "status": "done", "skipped": not out["built"], **summary}
