"""The campus flow on real Dask worker processes sharing one Prefect API."""

from __future__ import annotations

import os

import numpy as np
import pytest

from flows.campus import CampusRunFailed, run_campus
from flows.status import campus_status
from storage.patches.read import PatchStore
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import all_records
from tasks.config import CampusConfig


def _task_runs_on_server(api_url: str) -> int:
    """How many task runs the (single) test server has recorded."""
    import httpx

    r = httpx.post(f"{api_url}/task_runs/count", json={}, timeout=30)
    r.raise_for_status()
    return int(r.json())


def test_tiny_campus_on_dask_processes_then_resume(tiny_campus, tmp_path, prefect_api):
    cfg = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {"work_dir": str(tmp_path / "work")})
    before = _task_runs_on_server(prefect_api)
    summary = run_campus(cfg, progress=False)
    wd = WorkDir(cfg.work_dir)
    assert summary["tiles_failed"] == [] and summary["tiles_done"]
    recs = {r.unit: r for r in all_records(wd) if r.stage == "partition" and r.status == "done"}
    # the tiles ran in Dask worker processes, not in this process ...
    pids = {r.summary["worker"].split(":")[1] for r in recs.values()}
    assert str(os.getpid()) not in pids
    # ... and every task run the flow submitted was recorded by the one server of this test run (no
    # per-worker servers): scan, register, ingest, partition, outliers, merge, export nodes, quality, report
    n_tasks = summary["task_runs"]
    assert n_tasks >= 10
    assert _task_runs_on_server(prefect_api) - before == n_tasks
    # every MLS point is in exactly one patch of one tile
    from storage.formats.points import read_header

    n_las = sum(read_header(p).point_count for p in (tiny_campus / "mls").glob("*.laz"))
    assert sum(PatchStore(wd.tile_dir(t)).n_points for t in wd.done_tiles()) == n_las
    # labels from the synth defects reached the patch stores
    labels = [r for r in all_records(wd) if r.stage == "labels"]
    assert len(labels) == len(recs) and sum(r.summary["n_bad"] for r in labels) > 0
    stamps = {k: r.updated_at for k, r in recs.items()}

    again = run_campus(cfg, progress=False)  # second run: everything is done already
    assert again["tiles_done"] == summary["tiles_done"]
    recs2 = {r.unit: r for r in all_records(wd) if r.stage == "partition" and r.status == "done"}
    assert {k: r.updated_at for k, r in recs2.items()} == stamps  # no tile was redone
    assert (wd.report_dir / "patch_points_histogram.png").exists()
    # the whole output: a tileset of the merged tiles and the run report
    assert summary["output"]["tileset"] and (wd.root / "output" / "report.html").exists()


def test_bad_inputs_fail_only_their_tiles(tmp_path, handmade_campus, prefect_api, capsys):
    cfg = CampusConfig.from_yaml(handmade_campus(extra_stray=True))
    laz = tmp_path / "mls" / "west.laz"
    laz.write_bytes(laz.read_bytes()[: laz.stat().st_size // 2])  # truncated LAZ
    obj = tmp_path / "mesh" / "middle.obj"  # a mesh with nothing usable: every face indexes a missing vertex
    lines = ["f 999997 999998 999999" if line.startswith("f ") else line for line in obj.read_text().splitlines()]
    obj.write_text("\n".join(lines) + "\n")

    with pytest.raises(CampusRunFailed) as exc:
        run_campus(cfg, progress=False)
    st = campus_status(cfg.work_dir)
    failed = st["failed"]
    assert failed, "bad inputs must fail their tiles"
    bad = st["bad_inputs"]
    assert any("truncated" in e and "west.laz" in k for k, e in bad.items())
    assert any("no usable face" in e and "middle.obj" in k for k, e in bad.items())
    assert any("west.laz" in e for e in failed.values()) and any("middle.obj" in e for e in failed.values())
    x = lambda k: int(k.split("_")[0]) * 20 - 500_000
    west = {k for k, e in failed.items() if "west.laz" in e}
    assert all(x(k) < 40 for k in west)  # only tiles of the west region
    east_done = [k for k in st["done"] if 120 <= x(k) < 150]
    assert len(east_done) >= 2  # the healthy region is done
    assert st["empty"], "tiles inside the stray file's extent but without data are reported empty"
    assert "west.laz" in str(exc.value)
    # outputs of done tiles are valid patch stores
    for k in east_done:
        store = PatchStore(WorkDir(cfg.work_dir).root / "tiles" / k)
        assert store.n_points > 0 and np.all(store.patches()["n_faces"] >= 0)

    # ms3d status reports the failed tiles with their errors, and exits 1
    from flows.cli import main

    assert main(["status", cfg.work_dir]) == 1
    out = capsys.readouterr().out
    assert "FAILED" in out and "truncated" in out and "empty" in out
