"""A rerun maps only the units that must run: the planner decides from one read of each stage's records,
launches no task run for a stage that is up to date (campus-wide steps included), and the summary still
counts the skipped units. Inline (no Prefect), on the hand-made campus with every patch graded bad, so it
has regions to repair."""

from __future__ import annotations

import hashlib

import numpy as np

from flows.campus import InlineExecutor, run_campus
from storage.formats.points import PointChunk, write_points
from storage.workdir.layout import WorkDir
from synth.handmade import ORIGIN, region_mesh
from tasks.config import CampusConfig

_COUNTS = ("scan", "ingest", "partition", "repair", "merge")


class _Recording(InlineExecutor):
    """The inline executor, noting the units each mapped task was given and each task submitted."""

    def __init__(self):
        self.mapped: dict[str, list] = {}
        self.submitted: list[str] = []

    def map(self, tsk, batches, label, **consts):
        if batches:
            self.mapped.setdefault(tsk.name, []).extend(u for b in batches for u in b)
        return super().map(tsk, batches, label, **consts)

    def submit(self, tsk, *args):
        self.submitted.append(tsk.name)
        return super().submit(tsk, *args)


def _store_files(wd: WorkDir) -> dict[str, tuple]:
    """{work-dir relative path: (size, mtime_ns)} of every tile and region file (not rewritten), the
    content hash of every output file (the export may rewrite a file with the same bytes)."""
    out = {}
    for sub in ("tiles", "regions", "output"):
        for p in sorted((wd.root / sub).rglob("*")):
            if p.is_file():
                st = p.stat()
                out[str(p.relative_to(wd.root))] = (hashlib.sha256(p.read_bytes()).hexdigest(),) \
                    if sub == "output" else (st.st_size, st.st_mtime_ns)
    return out


def _rewrite_west_scan(root) -> None:
    """The west region's MLS file scanned again (other samples of the same surfaces)."""
    rng = np.random.default_rng(7)
    pts = np.asarray(region_mesh(0.0).sample(15_000, seed=3)) + rng.normal(0, 0.003, (15_000, 3)) + ORIGIN
    write_points(root / "mls" / "west.laz", PointChunk(xyz=pts, gps_time=np.sort(rng.uniform(0, 100, len(pts)))),
                 crs="EPSG:32650")


def test_reruns_map_only_what_must_run(handmade_campus):
    cfg_path = handmade_campus()
    cfg = CampusConfig.from_yaml(cfg_path, {
        "runner": "inline", "classify.enabled": False, "report.enabled": False, "repair.grades": "all"})
    wd = WorkDir(cfg.work_dir)
    first = _Recording()
    s1 = run_campus(cfg, executor=first)
    regions = sorted(first.mapped["repair"])
    assert regions and s1["stages"]["repair"]["run"] == len(regions)
    assert {"outliers", "regions"} <= set(first.submitted)
    files = _store_files(wd)

    # nothing changed: no task run at all, the same files untouched, the same counts (all skipped)
    again = _Recording()
    s2 = run_campus(cfg, executor=again)
    assert again.mapped == {} and again.submitted == []
    assert _store_files(wd) == files
    for stage in _COUNTS:
        assert s2["stages"][stage]["run"] == 0 and s2["stages"][stage]["failed"] == 0
        assert s2["stages"][stage]["skipped"] == s1["stages"][stage]["run"], stage
    assert s2["stages"]["repair"] == {"run": 0, "skipped": len(regions), "failed": 0, "units_run": []}

    # a region whose record is gone is redone, and only it
    (wd.manifest_dir / "region" / f"{regions[0]}.json").unlink()
    third = _Recording()
    s3 = run_campus(cfg, executor=third)
    assert third.mapped["repair"] == [regions[0]] and set(third.mapped) <= {"repair", "merge"}  # merge: its tiles
    assert s3["stages"]["repair"]["units_run"] == [regions[0]]
    assert s3["stages"]["repair"]["skipped"] == len(regions) - 1

    # one input changed: its scan and ingest units and the tiles it covers run, nothing else
    _rewrite_west_scan(cfg_path.parent)
    files = _store_files(wd)
    fourth = _Recording()
    s4 = run_campus(cfg, executor=fourth)
    assert [f["path"].rsplit("/", 1)[-1] for f in fourth.mapped["scan"]] == ["west.laz"]
    assert [u["key"] for u in fourth.mapped["ingest"]] and all(
        "west" in u["path"] for u in fourth.mapped["ingest"])
    west_tiles = set(fourth.mapped["partition"])
    all_tiles = {k.split("/")[1] for k in files if k.startswith("tiles/")}
    assert west_tiles and west_tiles < all_tiles
    assert s4["stages"]["partition"]["run"] == len(west_tiles)
    assert set(fourth.mapped.get("merge", [])) <= west_tiles
    untouched = {k: v for k, v in files.items() if k.startswith("tiles/") and k.split("/")[1] not in west_tiles}
    now = _store_files(wd)
    assert untouched and all(now.get(k) == v for k, v in untouched.items())
