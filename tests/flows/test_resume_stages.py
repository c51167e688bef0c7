"""Resume semantics of the stage functions (no Prefect): a changed input redoes only what it touches."""

from __future__ import annotations

from storage.ids import TileId
from storage.manifest import all_records
from storage.pointcloud_io import PointChunk, read_points, write_points
from storage.workdir import WorkDir
from tasks.config import CampusConfig
from tasks.ingest import InputFile, plan_units, run_ingest_unit, run_register
from tasks.patches import run_partition_tile


def _run_all(cfg):
    wd = WorkDir(cfg.work_dir)
    campus = run_register(cfg, wd)
    units = plan_units([InputFile(**r) for r in campus["inputs"]], cfg)
    for u in units:
        run_ingest_unit(u, cfg, wd, campus)
    out = {}
    for t in wd.staged_tiles():
        out[t.key] = run_partition_tile(t, cfg, wd)
    return wd, out


def test_changed_input_redoes_only_its_tiles(handmade_campus):
    cfg = CampusConfig.from_yaml(handmade_campus())
    wd, first = _run_all(cfg)
    assert all(not s.get("skipped") for s in first.values())
    _, second = _run_all(cfg)
    assert all(s.get("skipped") for s in second.values())  # nothing changed: everything skipped

    east = wd.root.parent / "mls" / "east.laz"
    pc = read_points(east)
    keep = pc.xyz[:, 1] - 4_000_000.0 < 15.0  # drop the northern half of the east scan
    write_points(east, PointChunk(xyz=pc.xyz[keep], gps_time=pc.gps_time[keep]), crs="EPSG:32650")
    _, third = _run_all(cfg)
    redone = {k for k, s in third.items() if not s.get("skipped")}
    assert redone and all(int(k.split("_")[0]) * 20 >= 100 for k in redone)  # only east tiles
    ingest = {r.unit: r for r in all_records(wd) if r.stage == "ingest"}
    assert all(r.status == "done" for r in ingest.values())
    n = sum(s.get("n_points", 0) for s in third.values())
    assert n == 2 * 20_000 + int(keep.sum())
    assert TileId(0, 0) in wd.done_tiles()
