"""The external merge of sorted runs writes the same store files as the in-memory partition."""

from __future__ import annotations

import hashlib
import json

import numpy as np
import pytest

from flows.campus import InlineExecutor, run_campus
from storage.contracts.staging import staged_files
from storage.frame import CampusFrame
from storage.patches.read import PatchStore
from storage.patches.schema import TileMeta
from synth.handmade import build_campus
from tasks.config import CampusConfig
from tasks.partition.stream import plan_blocks, stream_partition_tile


def _sha(p):
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def staged(tmp_path_factory):
    import storage.contracts.columns

    root = tmp_path_factory.mktemp("stream")
    cfg = CampusConfig.from_yaml(build_campus(root / "in", tile_size_m=40.0, subdivisions=4),
                                 {"work_dir": str(root / "work"), "runner": "inline"})
    with pytest.MonkeyPatch.context() as mp:  # small row groups: many cut points on a small tile
        mp.setattr(storage.contracts.columns, "RUN_ROW_GROUP", 256)
        run_campus(cfg, executor=InlineExecutor())
    frame = CampusFrame.from_json(json.loads((root / "work" / "campus.json").read_text())["frame"])
    return cfg, root / "work", frame


@pytest.mark.parametrize("budget_rows", [300, 2_000, 50_000])
def test_streamed_tile_equals_in_memory_tile(staged, tmp_path, budget_rows):
    cfg, work, frame = staged
    tiles = sorted(d for d in (work / "tiles").iterdir() if (d / "patches.parquet").exists())
    big = max(tiles, key=lambda d: PatchStore(d).n_points)
    parts = staged_files(type("W", (), {"root": work})(), big.name)
    meta = TileMeta(big.name, tuple(cfg.partition.patch_size_m), frame.crs)
    out = stream_partition_tile([p for p in parts if p.name.startswith("p")],
                                [p for p in parts if p.name.startswith("m")], tmp_path / big.name, meta, budget_rows)
    if budget_rows < 1000:
        assert out["blocks"] > 4  # really merged block by block
    for name in ("points.parquet", "faces.parquet", "patches.parquet"):
        assert _sha(tmp_path / big.name / name) == _sha(big / name), name
    assert PatchStore(tmp_path / big.name).n_points == out["n_points"] > 1000


def test_plan_blocks_bounds_rows_and_covers_every_key():
    rng = np.random.default_rng(0)
    groups = []
    for _ in range(6):  # six sorted runs over one key range, row groups of 100 rows
        keys = np.sort(rng.integers(0, 5000, 1000))
        groups.append(np.array([[keys[a], keys[a + 99], 100] for a in range(0, 1000, 100)]))
    blocks = plan_blocks(groups, 1500)
    assert blocks[0][0] == min(g[0, 0] for g in groups) and blocks[-1][1] == np.iinfo(np.int64).max
    assert all(b[0] == a[1] for a, b in zip(blocks, blocks[1:]))  # contiguous, disjoint
    allg = np.concatenate(groups)
    for lo, hi in blocks:
        touched = allg[(allg[:, 1] >= lo) & (allg[:, 0] < hi), 2].sum()
        assert touched <= 1500 or hi == next(c for c in np.unique(allg[:, 0]) if c > lo)


def test_the_stage_streams_when_the_budget_is_small(staged, tmp_path):
    from storage.ids import TileId
    from storage.workdir.layout import WorkDir
    from tasks.partition import run_partition_tile

    cfg, work, frame = staged
    tile = max((d for d in (work / "tiles").iterdir() if (d / "patches.parquet").exists()),
               key=lambda d: PatchStore(d).n_points)
    before = {n: _sha(tile / n) for n in ("points.parquet", "faces.parquet", "patches.parquet")}
    (work / "manifest.d" / "partition" / f"{tile.name}.json").unlink()
    res = run_partition_tile(TileId.from_key(tile.name), cfg, WorkDir(work), frame, force_stream=True)
    assert res["status"] == "done" and res["streamed"]
    assert {n: _sha(tile / n) for n in before} == before
