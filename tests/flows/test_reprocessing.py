"""Reprocessing on changing inputs: every change gives the stores of a clean run, and only the tiles
the change touches are redone. Runs the whole campus pipeline inline (no Prefect), so each case is a
few seconds; the Prefect/Dask path runs the same ``flows.campus.reprocess`` (tests/flows/test_campus_flow.py)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml

from flows.campus import CampusRunFailed, InlineExecutor, run_campus
from storage.formats.points import PointChunk, read_points, write_points
from storage.patches.read import PatchStore
from storage.workdir.layout import WorkDir
from tasks.config import CampusConfig

from .conftest import ORIGIN, build_campus, region_mesh

TILE = 20.0


# the stages these tests are about end with partition; the later ones (on their own inputs) are covered by
# test_removed_input_through_the_whole_pipeline and the stages' own tests
EARLY = {"classify.enabled": False, "repair.enabled": False, "report.enabled": False}


def _cfg(path: Path, work: Path, full: bool = False, **over) -> CampusConfig:
    return CampusConfig.from_yaml(path, {"work_dir": str(work), "runner": "inline", **({} if full else EARLY), **over})


def _run(cfg: CampusConfig) -> dict:
    return run_campus(cfg, executor=InlineExecutor())


def _stores(work: Path) -> dict[str, dict]:
    """Every store file of every tile as Arrow tables (data and metadata)."""
    out = {}
    for d in sorted((work / "tiles").iterdir()):
        out[d.name] = {f.name: pq.read_table(f) for f in sorted(d.glob("*.parquet"))}
    return out


def _assert_same_stores(a: Path, b: Path) -> None:
    sa, sb = _stores(a), _stores(b)
    assert sorted(sa) == sorted(sb)
    for tile in sa:
        assert sorted(sa[tile]) == sorted(sb[tile]), tile
        for name, table in sa[tile].items():
            other = sb[tile][name]
            assert table.schema.equals(other.schema, check_metadata=True), f"{tile}/{name}: schema or metadata"
            for c in table.column_names:  # bitwise, so NaN uv equal NaN uv
                assert np.asarray(table[c]).tobytes() == np.asarray(other[c]).tobytes(), f"{tile}/{name}.{c}"
    assert not list((a / "staging").rglob(".*")), "temporary staging files left behind"


def _clean_run(config: Path, tmp: Path, full: bool = False) -> Path:
    work = tmp / "clean"
    shutil.rmtree(work, ignore_errors=True)
    _run(_cfg(config, work, full))
    return work


def _region_of(tile_key: str) -> str:
    x = int(tile_key.split("_")[0]) * TILE - ORIGIN[0]
    return "west" if x < 45 else "middle" if x < 105 else "east"


@pytest.fixture
def campus(tmp_path):
    config = build_campus(tmp_path / "in", tile_size_m=TILE)
    work = tmp_path / "work"
    first = _run(_cfg(config, work))
    assert first["stages"]["partition"]["run"] > 0
    return config, work


def _redone_regions(summary: dict) -> set[str]:
    return {_region_of(k) for k in summary["stages"]["partition"]["units_run"]}


def test_unchanged_rerun_skips_everything(campus):
    config, work = campus
    s = _run(_cfg(config, work))
    assert all(c["run"] == 0 for c in s["stages"].values()), s["stages"]


def test_removed_input(campus, tmp_path):
    config, work = campus
    (config.parent / "mls" / "east.laz").unlink()
    s = _run(_cfg(config, work))
    assert _redone_regions(s) == {"east"}
    _assert_same_stores(work, _clean_run(config, tmp_path))
    n_east = sum(PatchStore(work / "tiles" / t).n_points for t in s["tiles_done"] if _region_of(t) == "east")
    assert n_east == 0  # the points of the deleted strip are gone


def test_removed_input_through_the_whole_pipeline(tmp_path):
    """Grades, the region plan and the merged tile meshes after a removed strip equal a clean run's."""
    import json

    config = build_campus(tmp_path / "in", tile_size_m=TILE)
    work = tmp_path / "work"
    _run(_cfg(config, work, full=True))
    (config.parent / "mls" / "east.laz").unlink()
    s = _run(_cfg(config, work, full=True))
    assert _redone_regions(s) == {"east"} and {_region_of(t) for t in s["stages"]["classify"]["units_run"]} == {"east"}
    clean = _clean_run(config, tmp_path, full=True)
    _assert_same_stores(work, clean)  # incl. grades.parquet
    plan = lambda w: [r["key"] for r in json.loads((w / "regions" / "regions.json").read_text())["regions"]]
    assert plan(work) == plan(clean)
    for t in sorted((clean / "tiles").iterdir()):
        if (t / "merged.npz").exists():
            a, b = np.load(t / "merged.npz"), np.load(work / "tiles" / t.name / "merged.npz")
            assert sorted(a.files) == sorted(b.files)
            for k in a.files:
                assert np.asarray(a[k]).tobytes() == np.asarray(b[k]).tobytes(), f"{t.name} merged {k}"


def test_added_input(campus, tmp_path):
    config, work = campus
    rng = np.random.default_rng(9)
    xyz = rng.uniform([125, 2, 0.5], [140, 28, 3], (3000, 3)) + ORIGIN
    write_points(config.parent / "mls" / "east-extra.laz", PointChunk(xyz=xyz, gps_time=np.zeros(len(xyz))),
                 crs="EPSG:32650")
    s = _run(_cfg(config, work))
    assert _redone_regions(s) == {"east"}
    assert s["stages"]["ingest"]["run"] == 1  # only the new file's unit
    _assert_same_stores(work, _clean_run(config, tmp_path))


def test_renamed_input(campus, tmp_path):
    config, work = campus
    (config.parent / "mls" / "west.laz").rename(config.parent / "mls" / "west-renamed.laz")
    s = _run(_cfg(config, work))
    assert _redone_regions(s) == {"west"}
    _assert_same_stores(work, _clean_run(config, tmp_path))


def test_shrunk_input(campus, tmp_path):
    config, work = campus
    east = config.parent / "mls" / "east.laz"
    pc = read_points(east)
    keep = pc.xyz[:, 1] - ORIGIN[1] < 15.0
    write_points(east, pc.take(keep), crs="EPSG:32650")
    s = _run(_cfg(config, work))
    assert _redone_regions(s) == {"east"}
    _assert_same_stores(work, _clean_run(config, tmp_path))


def test_reordered_inputs_change_nothing(campus):
    config, work = campus
    doc = yaml.safe_load(config.read_text())
    doc["inputs"]["points"] = [f"mls/{n}.laz" for n in ("east", "west", "middle")]
    doc["inputs"]["mesh"] = [f"mesh/{n}.obj" for n in ("middle", "east", "west")]
    config.write_text(yaml.safe_dump(doc))
    s = _run(_cfg(config, work))
    assert all(c["run"] == 0 for c in s["stages"].values()), s["stages"]


def test_stray_files_are_skipped_and_listed(campus):
    config, work = campus
    (config.parent / "mls" / "readme.txt").write_text("notes from the survey crew\n")
    (config.parent / "mls" / "empty.laz").write_bytes(b"")
    (config.parent / "mls" / "garbage.laz").write_bytes(b"\x00\x01not a laz file" * 100)
    (config.parent / "mls" / "folder.laz").mkdir()
    with pytest.raises(CampusRunFailed) as e:
        _run(_cfg(config, work))
    s = e.value.summary
    assert [Path(p).name for p, _ in s["skipped_files"]] == ["readme.txt"]
    assert set(s["tiles_failed"]) == set()  # no tile fails: none of the bad files has a known extent
    assert s["incomplete"] and {Path(p).name for p in s["incomplete"]} >= {"empty.laz", "garbage.laz"}
    assert "INCOMPLETE" in str(e.value)
    assert s["stages"]["partition"]["run"] == 0  # the good tiles were not touched


def test_campus_growing_west_keeps_patch_ids(campus, tmp_path):
    config, work = campus
    middle = sorted(t for t in _stores(work) if _region_of(t) == "middle")
    before = {t: PatchStore(work / "tiles" / t).patches() for t in middle}
    # a new region 1.5 km to the west moves the campus origin by 2 km
    from storage.formats.meshes import write_obj

    m = region_mesh(-1500.0)
    write_obj(config.parent / "mesh" / "far-west.obj", np.asarray(m.vertices), np.asarray(m.faces))
    s = _run(_cfg(config, work))
    assert s["stages"]["partition"]["run"] >= len(middle)  # the frame moved: every tile is rebuilt
    for t in middle:
        after = PatchStore(work / "tiles" / t).patches()
        assert np.array_equal(after["patch"], before[t]["patch"])  # same places, same ids
        assert np.array_equal(after["n_faces"], before[t]["n_faces"])
        assert np.array_equal(after["n_points"], before[t]["n_points"])
    _assert_same_stores(work, _clean_run(config, tmp_path))


def test_labels_file_edited_in_place(campus):
    config, work = campus
    wd = WorkDir(work)
    tile = next(t for t in sorted(_stores(work)) if _region_of(t) == "middle" and
                (work / "tiles" / t / "patches.parquet").exists())
    keys = PatchStore(wd.root / "tiles" / tile).patches()
    ijk = np.stack([keys["i"], keys["j"], keys["k"]], axis=1)
    labels = config.parent / "labels.csv"
    labels.write_text("i,j,k,label\n" + "".join(f"{i},{j},{k},1\n" for i, j, k in ijk[:3]))
    doc = yaml.safe_load(config.read_text())
    doc["inputs"]["labels"] = "labels.csv"
    config.write_text(yaml.safe_dump(doc))
    s = _run(_cfg(config, work))
    assert s["stages"]["partition"]["run"] == 0  # labels never rewrite the partition output
    lab = PatchStore(wd.root / "tiles" / tile).side("labels")["label"]
    assert lab[:3].tolist() == [1, 1, 1] and lab[3:].sum() == 0
    labels.write_text("i,j,k,label\n" + "".join(f"{i},{j},{k},1\n" for i, j, k in ijk[3:5]))  # edit in place
    _run(_cfg(config, work))
    lab = PatchStore(wd.root / "tiles" / tile).side("labels")["label"]
    assert lab[:3].tolist() == [0, 0, 0] and lab[3:5].tolist() == [1, 1]


@pytest.mark.slow
def test_renamed_inputs_in_another_run_order_give_the_same_stores_and_grades(tiny_campus, tmp_path):
    """The same two MLS strips under other names arrive in the other run order (runs follow source ids, hashes
    of the paths). Registration samples the inputs by coordinates and the partition merges runs in the order of
    their content digests, so the transform, the points tables and the grades are the same bitwise (but for the
    source ids). Once they followed the runs: the ~200 pairs above the cues'
    point cap subsampled other points, and an S3 copy of a campus graded differently from the local one."""
    from storage.inputs.identity import assign_source_ids

    def first_strip_first(campus: Path, names: tuple[str, str]) -> bool:
        paths = [str((campus / "mls" / n).resolve()) for n in names]
        ids = assign_source_ids(paths)
        return ids[paths[0]] < ids[paths[1]]

    tables, order, reg = {}, {}, {}
    for run in ("one", "other"):
        campus = tmp_path / run / "campus"
        shutil.copytree(tiny_campus, campus)
        names = ("s0.laz", "s1.laz")
        if run == "other":  # names under which both the paths and the strips' runs sort the other way round
            names = next((f"z{n}.laz", "s1.laz") for n in range(1000)
                         if first_strip_first(campus, (f"z{n}.laz", "s1.laz")) != order["one"])
        order[run] = first_strip_first(campus, names)
        for strip, new in zip(sorted((campus / "mls").glob("*.laz")), names):
            strip.rename(campus / "mls" / new)
        work = tmp_path / run / "work"
        _run(CampusConfig.from_yaml(campus / "campus.yaml", {
            "work_dir": str(work), "runner": "inline", "registration.mode": "auto", "repair.enabled": False,
            "report.enabled": False}))
        reg[run] = json.loads((work / "registration.json").read_text())
        tables[run] = {f"{d.name}/{f}": pq.read_table(d / f) for d in sorted((work / "tiles").iterdir())
                       for f in ("points.parquet", "grades.parquet") if (d / f).exists()}
    assert order["one"] != order["other"]  # the precondition: the runs did come in the other order
    # the registration samples and subsamples by coordinates, not by source ids: the same transform
    assert reg["one"]["matrix"] == reg["other"]["matrix"] and reg["one"]["method"].startswith("sac-ia")
    assert sorted(tables["one"]) == sorted(tables["other"]) and any(k.endswith("grades.parquet") for k in tables["one"])
    for key, t in tables["one"].items():
        for c in t.column_names:  # bitwise, so an ungraded NaN equals an ungraded NaN
            if c != "source":
                assert np.asarray(t[c]).tobytes() == np.asarray(tables["other"][key][c]).tobytes(), f"{key}.{c}"
