"""Ingest with ``inputs.points_bounds``: a point cloud wider than the campus is ingested only inside the box; a
COPC input gives the same staging rows as the same points in a LAS file while decompressing only the octree
nodes over the box; files outside the box plan no unit and cover no tile."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from flows.campus import InlineExecutor, scan_inputs
from storage.contracts.columns import RunReader
from storage.formats import points as points_module
from storage.formats.copc import CopcReadStats, iter_copc
from storage.formats.points import PointChunk, write_points
from storage.inputs.identity import InputFile
from storage.workdir.layout import WorkDir
from synth.copc import write_copc
from tasks.config import CampusConfig
from tasks.ingest import input_tiles, plan_units, run_ingest_unit
from tasks.scan import campus_frame, clip_point_records, outside_box, points_box

E0, N0 = 500_000.0, 4_000_000.0


def street(n: int = 24_000, seed: int = 1) -> PointChunk:
    """A 2.5 km x 60 m strip of street points (x 498,500..501,000) on a 1 mm lattice, every field set."""
    rng = np.random.default_rng(seed)
    mm = rng.integers(0, [2_500_000, 60_000, 6_000], size=(n, 3))
    return PointChunk(xyz=np.array([E0 - 1500, N0 - 30, 0.0]) + mm / 1000.0,
                      rgb=rng.integers(0, 65536, (n, 3)).astype(np.uint16),
                      intensity=rng.integers(0, 65536, n).astype(np.uint16),
                      gps_time=np.sort(rng.uniform(3e5, 3.1e5, n)),
                      classification=rng.integers(0, 20, n).astype(np.uint8))


def _ingest(tmp_path, name: str, write) -> tuple[dict, list, CampusConfig, list]:
    """Scan, plan and ingest a 4 m box mesh at (E0, N0) with the points ``write`` puts at ``name``; returns the
    staging columns (source id left out), the units, the config and the scan records."""
    root = tmp_path / name
    (root / "mesh").mkdir(parents=True)
    trimesh.creation.box((4, 4, 4)).export(root / "mesh" / "box.glb")
    write(root / name)
    cfg = CampusConfig.model_validate({
        "work_dir": str(root / "w"), "tiling": {"chunk_points": 5_000},
        "inputs": {"mesh": [str(root / "mesh")], "points": [str(root / name)], "mesh_offset": [E0, N0, 0],
                   "points_bounds": "mesh"},
        "registration": {"mode": "off"}})
    wd = WorkDir(cfg.work_dir)
    records, frame, *_ = scan_inputs(cfg, wd, InlineExecutor())
    units = plan_units(records, cfg.tiling.chunk_points, points_box(records, cfg.inputs.points_bounds, cfg.grid()))
    for u in units:
        if u.kind == "points":
            run_ingest_unit(u, cfg, wd, frame, np.eye(4))
    runs = [RunReader(p).read() for p in sorted((wd.root / "staging").rglob("p*.arrow"))]
    cols = {k: np.concatenate([r[k] for r in runs]) for k in runs[0] if k != "source"}
    order = np.lexsort((cols["gps_time"], cols["z"], cols["y"], cols["x"]))
    return {k: v[order] for k, v in cols.items()}, units, cfg, records


def test_copc_ingest_equals_las_inside_the_mesh_box(tmp_path, monkeypatch):
    src = street()
    stats = CopcReadStats()
    monkeypatch.setattr(points_module, "iter_copc", lambda *a, **k: iter_copc(*a, **k, stats=stats))
    las, _, cfg, records = _ingest(tmp_path, "scan.las", lambda p: write_points(p, src, crs="EPSG:32650"))
    copc, copc_units, _, _ = _ingest(tmp_path, "scan.copc.laz",
                                     lambda p: write_copc(p, src, crs="EPSG:32650", max_level=3, span=4))
    box = points_box(records, "mesh", cfg.grid())
    assert box == (E0 - 200, N0 - 200, E0 + 200, N0 + 200)  # the 4 m mesh grown by a tile, snapped to 100 m
    inside = ((src.xyz[:, 0] >= box[0]) & (src.xyz[:, 0] <= box[2])).sum()
    assert 0 < inside < len(src) / 3
    assert len(las["x"]) == len(copc["x"]) == inside
    for k in las:
        np.testing.assert_array_equal(las[k], copc[k], err_msg=k)
    assert [u.bounds for u in copc_units if u.kind == "points"] == [box] * 5
    assert stats.points_returned == inside and stats.points_decoded < len(src) / 2
    # the campus origin and the tiles the points cover come from the box, not from the 2.5 km strip
    frame = campus_frame(records, cfg)
    assert frame.origin[0] == 499_000.0  # 498,000 from the whole strip
    tiles = input_tiles(records, frame, np.eye(4), cfg.grid(), box)
    (pts,) = [r.source for r in records if r.kind == "points"]
    assert sorted({int(k.split("_")[0]) for k in tiles[pts]}) == list(range(4997, 5003))
    assert len(input_tiles(records, frame, np.eye(4), cfg.grid())[pts]) > 25  # the whole strip without a box


@pytest.mark.parametrize(("lo", "hi", "outside"), [((0.0, 0.0), (8.0, 8.0), True),
                                                   ((5.0, 5.0), (20.0, 20.0), False)])
def test_a_point_file_outside_the_box_plans_no_unit(lo, hi, outside):
    rec = InputFile(3, "far.laz", "points", "f", count=10_000, lo=[*lo, 0.0], hi=[*hi, 1.0])
    box = (9.0, 9.0, 30.0, 30.0)
    assert outside_box(rec, box) is outside
    assert (plan_units([rec], 5_000, box) == []) is outside
    assert clip_point_records([rec], box) == ([] if outside else [InputFile(3, "far.laz", "points", "f", count=10_000,
                                                                            lo=[9.0, 9.0, 0.0], hi=[*hi, 1.0])])
    assert all(u.bounds == box for u in plan_units([rec], 5_000, box))
    assert plan_units([rec], 5_000)[0].bounds is None


def test_registration_samples_a_copc_from_its_coarse_levels_in_the_box(tmp_path):
    from tasks.register.stage import sample_points_for_registration

    path = tmp_path / "street.copc.laz"
    src = street()
    write_copc(path, src, max_level=4, span=8)
    cfg = CampusConfig.model_validate({"inputs": {"points": [str(path)]}})
    rec = InputFile(0, str(path), "points", "f", count=len(src), lo=src.xyz.min(0).tolist(), hi=src.xyz.max(0).tolist())
    box = (E0 - 200, N0 - 200, E0 + 200, N0 + 200)
    got = sample_points_for_registration(rec, 1_000, cfg, box=box)
    inside = src.xyz[(src.xyz[:, 0] >= box[0]) & (src.xyz[:, 0] <= box[2])]
    assert 500 <= len(got) <= 2 * 1_000 < len(inside)
    assert (got[:, 0] >= box[0]).all() and (got[:, 0] <= box[2]).all()
    mm = np.round(np.concatenate([got, inside]) * 1000).astype(np.int64)
    assert len(np.unique(mm, axis=0)) == len(inside)  # real points of the box


def test_a_points_box_missing_every_point_file_is_one_line_naming_their_extent():
    from storage.errors import InputError
    from storage.inputs.identity import InputFile
    from tasks.scan import files_outside_box

    a = InputFile(0, "a.laz", "points", "f", lo=[500_000.0, 4_000_000.0, 0.0], hi=[500_100.0, 4_000_050.0, 9.0])
    m = InputFile(1, "m.obj", "mesh", "g", lo=[0.0, 0.0, 0.0], hi=[10.0, 10.0, 5.0])
    assert files_outside_box([a, m], (499_900.0, 3_999_900.0, 500_200.0, 4_000_200.0)) == []
    assert files_outside_box([a, m], None) == []
    with pytest.raises(InputError, match=r"overlaps no MLS point file .*x 500000.0\.\.500100.0") as e:
        files_outside_box([a, m], (0.0, 0.0, 100.0, 100.0))  # a box in local metres for a UTM scan
    assert "\n" not in str(e.value)
