import json

from storage.workdir.layout import WorkDir
from storage.workdir.manifest import (
    ManifestRecord,
    all_records,
    consolidate,
    is_done,
    params_hash,
    write_record,
)


def test_done_needs_matching_fingerprints_and_outputs(tmp_path):
    wd = WorkDir(tmp_path)
    (tmp_path / "out.bin").write_bytes(b"x")
    write_record(wd, ManifestRecord("partition", "0_0", "done", "fp1", "ph1", outputs=["out.bin"]))
    assert is_done(wd, "partition", "0_0", "fp1", "ph1") is not None
    assert is_done(wd, "partition", "0_0", "fp2", "ph1") is None  # input changed
    assert is_done(wd, "partition", "0_0", "fp1", "ph2") is None  # parameters changed
    (tmp_path / "out.bin").unlink()
    assert is_done(wd, "partition", "0_0", "fp1", "ph1") is None  # output gone


def test_failed_unit_is_not_done_and_consolidates(tmp_path):
    import pyarrow.parquet as pq

    wd = WorkDir(tmp_path)
    write_record(wd, ManifestRecord("ingest", "p000-00000", "failed", "a", "b", error="x.laz: truncated"))
    write_record(wd, ManifestRecord("partition", "1_2", "done", "a", "b", summary={"n_points": 5}))
    assert is_done(wd, "ingest", "p000-00000", "a", "b") is None
    assert {r.unit for r in all_records(wd)} == {"p000-00000", "1_2"}
    t = pq.read_table(consolidate(wd)).to_pylist()
    assert sorted(r["status"] for r in t) == ["done", "failed"]
    assert json.loads([r for r in t if r["unit"] == "1_2"][0]["summary"]) == {"n_points": 5}


def test_params_hash_is_order_independent():
    assert params_hash({"a": 1, "b": [1, 2]}) == params_hash({"b": [1, 2], "a": 1})
    assert params_hash({"a": 1}) != params_hash({"a": 2})
