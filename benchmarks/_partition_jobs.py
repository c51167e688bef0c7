"""The measured jobs of ``benchmarks/partition_bench.py``: each runs in a fresh single-threaded process
(``partition_bench.py --child``, which sets the thread variables before numpy loads) and returns its row
count with wall and CPU seconds (and peak RSS for the tile task)."""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass
class Timing:
    wall: float = 0.0
    cpu: float = 0.0


class timed:
    """``with timed() as t:`` measures the block's wall and process CPU seconds."""

    def __enter__(self) -> Timing:
        self.t = Timing()
        self.w, self.c = time.perf_counter(), time.process_time()
        return self.t

    def __exit__(self, *exc):
        self.t.wall, self.t.cpu = time.perf_counter() - self.w, time.process_time() - self.c


def _peak_rss_bytes() -> int:
    """VmHWM of this process (not getrusage: a child's ru_maxrss carries the parent's peak)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return 0


def _rss_bytes() -> int:
    import psutil

    return psutil.Process().memory_info().rss


# ----------------------------------------------------------------------------------- measured jobs


def job_laspy_read(files: list[str]) -> dict:
    """laspy.read + every field ms3d keeps as numpy arrays."""
    import laspy

    n = 0
    with timed() as t:
        for f in files:
            las = laspy.read(f)
            xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1)
            _ = (np.asarray(las.intensity), np.asarray(las.gps_time), np.asarray(las.classification),
                 np.stack([np.asarray(las.red), np.asarray(las.green), np.asarray(las.blue)], axis=1))
            n += len(xyz)
    return {"n": n, "wall": t.wall, "cpu": t.cpu}


def job_ms3d_read(files: list[str], chunk: int) -> dict:
    from storage.formats.points import iter_points

    n = 0
    with timed() as t:
        for f in files:
            for c in iter_points(f, chunk):
                n += len(c)
    return {"n": n, "wall": t.wall, "cpu": t.cpu}


def job_ingest(units: list[dict], cfg: dict, wd: str, frame: dict, matrix) -> dict:
    from storage.frame import CampusFrame
    from storage.workdir.layout import WorkDir
    from tasks.config import CampusConfig
    from tasks.ingest import IngestUnit, run_ingest_unit

    cfg_m, w, fr = CampusConfig.model_validate(cfg), WorkDir(wd), CampusFrame.from_json(frame)
    m = np.asarray(matrix, np.float64)
    n = 0
    with timed() as t:
        for u in units:
            n += run_ingest_unit(IngestUnit(**u), cfg_m, w, fr, m)["rows"]
    return {"n": n, "wall": t.wall, "cpu": t.cpu}


def job_partition_points(tiles: list[str], wd: str, out: str, cfg: dict, frame: dict) -> dict:
    """The partition stage's store writer on the point runs only (what the baseline does)."""
    from storage.frame import CampusFrame
    from storage.patches.schema import TileMeta
    from tasks.config import CampusConfig
    from tasks.partition import write_tile_store

    cfg_m, fr = CampusConfig.model_validate(cfg), CampusFrame.from_json(frame)
    n = 0
    with timed() as t:
        for k in tiles:
            runs = sorted(p for p in (Path(wd) / "staging" / k).glob("p*.arrow"))
            if runs:
                meta = TileMeta(k, tuple(cfg_m.partition.patch_size_m), fr.crs)
                n += write_tile_store(runs, Path(out) / k, meta, 2**40)["n_points"]
    return {"n": n, "wall": t.wall, "cpu": t.cpu}


def job_baseline(files: list[str], origin, matrix, patch_size, tile_size_m: float, out: str) -> dict:
    """The naive script: laspy + pandas, same transform, ids, grouping, sorting and Parquet per tile."""
    import laspy
    import pandas as pd

    m = np.asarray(matrix, np.float64)
    sx, sy, sz = patch_size
    with timed() as t:
        frames = []
        for f in files:
            las = laspy.read(f)
            xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=1) - origin
            xyz = xyz @ m[:3, :3].T + m[:3, 3]
            frames.append(pd.DataFrame({
                "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
                "z": xyz[:, 2].astype(np.float32),
                "i": np.floor((xyz[:, 0] + origin[0]) / sx).astype("int64"),
                "j": np.floor((xyz[:, 1] + origin[1]) / sy).astype("int64"),
                "k": np.floor((xyz[:, 2] + origin[2]) / sz).astype("int64"),
                "intensity": np.asarray(las.intensity), "gps_time": np.asarray(las.gps_time),
                "red": np.asarray(las.red), "green": np.asarray(las.green), "blue": np.asarray(las.blue),
                "classification": np.asarray(las.classification)}))
        df = pd.concat(frames, ignore_index=True)
        del frames
        df["tx"] = np.floor((df["i"] + 0.5) * sx / tile_size_m).astype("int64")  # tile of the patch centre
        df["ty"] = np.floor((df["j"] + 0.5) * sy / tile_size_m).astype("int64")
        for (tx, ty), g in df.groupby(["tx", "ty"]):
            g = g.drop(columns=["tx", "ty"]).sort_values(["i", "j", "k"], kind="stable")
            patches = g.groupby(["i", "j", "k"]).agg(
                n_points=("x", "size"), xmin=("x", "min"), ymin=("y", "min"), zmin=("z", "min"),
                xmax=("x", "max"), ymax=("y", "max"), zmax=("z", "max")).reset_index()
            d = Path(out) / f"{tx}_{ty}"
            d.mkdir(parents=True, exist_ok=True)
            g.to_parquet(d / "points.parquet", index=False)
            patches.to_parquet(d / "patches.parquet", index=False)
    return {"n": len(df), "wall": t.wall, "cpu": t.cpu}


def job_tile_rss(wd: str, tile: str, origin: list, budget_mb: int, force_stream: bool) -> dict:
    import importlib

    from storage.frame import CampusFrame
    from storage.ids import TileId
    from storage.workdir.layout import WorkDir
    from tasks.config import CampusConfig
    from tasks.partition import run_partition_tile

    for lazy in ("storage.patches", "tasks.partition.stream", "pyarrow.parquet"):
        importlib.import_module(lazy)
    cfg = CampusConfig.model_validate({"work_dir": wd, "partition": {"memory_budget_mb": budget_mb}})
    w = WorkDir(wd)
    (w.manifest_dir / "partition" / f"{tile}.json").unlink(missing_ok=True)
    shutil.rmtree(w.tile_dir(TileId.from_key(tile)), ignore_errors=True)
    rss0 = _rss_bytes()
    with timed() as t:
        s = run_partition_tile(TileId.from_key(tile), cfg, w, CampusFrame(tuple(origin), "EPSG:32650"),
                               force_stream=force_stream)
    shutil.rmtree(w.tile_dir(TileId.from_key(tile)), ignore_errors=True)
    return {"rss_imports": rss0, "peak_rss": _peak_rss_bytes(), "wall": t.wall, "cpu": t.cpu,
            "n": s.get("n_points", 0), "streamed": s.get("streamed"), "status": s["status"], "error": s.get("error")}


JOBS = {f.__name__: f for f in (job_laspy_read, job_ms3d_read, job_ingest, job_partition_points, job_baseline,
                                job_tile_rss)}
