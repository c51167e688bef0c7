"""The planner of ``tasks.units``: one read of a stage's records decides exactly what run_unit would skip."""

from storage.workdir.layout import WorkDir
from storage.workdir.manifest import ManifestRecord, read_stage_records, write_record
from tasks.units import Done, pending_units, run_unit


def _ran(wd, stage, unit, fp, params, log):
    def work():
        log.append(unit)
        (wd.root / f"{unit}.out").write_text(unit)
        return Done(outputs=[f"{unit}.out"], summary={"n": len(unit)})

    return run_unit(wd, stage, unit, fp, params, work)


def test_read_stage_records_reads_one_stage_and_ignores_foreign_files(tmp_path):
    wd = WorkDir(tmp_path)
    write_record(wd, ManifestRecord("region", "r1", "done", "a", "b"))
    write_record(wd, ManifestRecord("region", "r2", "failed", "a", "b", error="x"))
    write_record(wd, ManifestRecord("merge", "0_0", "done", "a", "b"))
    d = wd.manifest_dir / "region"
    (d / "broken.json").write_text("{not json")
    (d / ".r3.json.abc.tmp.json").write_text("{}")  # a record being written
    (d / "notes.txt").write_text("x")
    recs = read_stage_records(wd, "region")
    assert sorted(recs) == ["r1", "r2"]
    assert recs["r2"].status == "failed"
    assert read_stage_records(wd, "nothing") == {}


def test_pending_units_skips_exactly_what_run_unit_skips(tmp_path):
    wd = WorkDir(tmp_path)
    log: list[str] = []
    fps = {f"u{i}": f"fp{i}" for i in range(6)}
    for u, fp in fps.items():
        _ran(wd, "region", u, fp, {"p": 1}, log)
    todo, skipped = pending_units(wd, "region", fps, {"p": 1})
    assert todo == [] and log == list(fps)
    # a planned skip reports what run_unit's own skip reports (the summary counts skipped units from it)
    assert skipped == [_ran(wd, "region", u, fp, {"p": 1}, log) for u, fp in fps.items()]
    assert log == list(fps) and all(s["skipped"] and s["n"] == 2 for s in skipped)
    # u1's input changed, u2's output vanished, u3 failed last time, u6 is new
    changed = {**fps, "u1": "fp1-new", "u6": "fp6"}
    (tmp_path / "u2.out").unlink()
    write_record(wd, ManifestRecord("region", "u3", "failed", "fp3", "x", error="bad"))
    todo, skipped = pending_units(wd, "region", changed, {"p": 1})
    assert todo == ["u1", "u2", "u3", "u6"]
    assert [s["unit"] for s in skipped] == ["u0", "u4", "u5"]
    assert all(s["skipped"] and s["status"] == "done" for s in skipped)
    # the run function agrees unit by unit: it redoes the same four and skips the rest
    log.clear()
    results = {u: _ran(wd, "region", u, fp, {"p": 1}, log) for u, fp in changed.items()}
    assert sorted(log) == todo
    assert {u for u, r in results.items() if r["skipped"]} == {"u0", "u4", "u5"}
    # each redone unit's summary (and record) says why it ran again; a new unit says nothing
    assert {u: results[u].get("redo") for u in todo} == {
        "u1": "inputs changed", "u2": "output missing: u2.out", "u3": "last run failed", "u6": None}
    # other parameters: everything runs
    assert pending_units(wd, "region", changed, {"p": 2})[0] == list(changed)
