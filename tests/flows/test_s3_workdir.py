"""A work dir on S3 used through per-process mirrors (storage.objstore.mirror, flows.remote), against moto's
S3 server on 127.0.0.1: a commit is seen whole by another process's mirror (files, producer mtimes,
deletions), a task killed between writing its objects and recording them leaves nothing trusted, and the
hand-made campus run with inputs and work dir on S3 equals the local run by content and reruns as a no-op
from a fresh mirror."""

from __future__ import annotations

import json
import os
import shutil
import uuid
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from synth.handmade import build_campus

BUCKET = "ms3d-workdir-test"
KEY_ID = "AKIAMS3DWORKDIRKEY01"
SECRET = "ms3d-workdir-secret-DO-NOT-LOG-9e1d"
IDENTITY = {"source", "vid0", "vid1", "vid2"}  # derived from the inputs' paths / URLs: differ by design


@pytest.fixture(scope="module")
def s3_server(moto_s3):
    """The session's moto S3 server on 127.0.0.1 with this module's bucket; yields the endpoint URL."""
    return moto_s3(BUCKET, KEY_ID, SECRET)


@pytest.fixture
def s3(s3_server, monkeypatch, tmp_path):
    """AWS environment on the local server, a fresh cache; yields the test's URL prefix."""
    from storage.inputs import remote as remote_inputs
    from storage.objstore import mirror as remote_workdir

    for k in ("AWS_PROFILE", "AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    for k, v in {"AWS_ENDPOINT_URL": s3_server, "AWS_ACCESS_KEY_ID": KEY_ID, "AWS_SECRET_ACCESS_KEY": SECRET,
                 "AWS_DEFAULT_REGION": "us-east-1", "MS3D_CACHE": str(tmp_path / "cache-a")}.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setattr(remote_inputs, "_STORES", {})
    monkeypatch.setattr(remote_workdir, "_MIRRORS", {})
    return f"s3://{BUCKET}/{uuid.uuid4().hex[:10]}"


def fresh_process(monkeypatch, cache: Path) -> None:
    """Look at the bucket as another process would: an empty cache and no mirror in memory."""
    from storage.inputs import remote as remote_inputs
    from storage.objstore import mirror as remote_workdir

    monkeypatch.setenv("MS3D_CACHE", str(cache))
    monkeypatch.setattr(remote_inputs, "_STORES", {})
    monkeypatch.setattr(remote_workdir, "_MIRRORS", {})


def upload(folder: Path, url: str) -> None:
    from storage.objstore.store import open_store

    store = open_store(url)
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            store.put_file(p.relative_to(folder).as_posix(), p)


def _texture_names(t) -> list[str] | None:
    """A faces table's texture list as file names: its ``texture`` column indexes a per-tile list in the
    order of the staged runs (source ids), and holds the staging process's paths."""
    from storage.patches.schema import META_KEY

    raw = (t.schema.metadata or {}).get(META_KEY)
    return [Path(p).name for p in json.loads(raw).get("textures", [])] if raw else None


def tables_by_content(work: Path) -> dict:
    """Every tile's parquet tables as sorted rows (identity columns left out, texture indices as texture file
    names, NaN made comparable) and its merged triangles."""
    out = {}
    for d in sorted((work / "tiles").iterdir()):
        for f in sorted(d.glob("*.parquet")):
            t = pq.read_table(f)
            cols = [c for c in t.column_names if c not in IDENTITY]
            arrays = [t.column(c).to_numpy(zero_copy_only=False) for c in cols]
            arrays = [np.nan_to_num(a, nan=-1e30).tolist() if a.dtype.kind == "f" else a.tolist() for a in arrays]
            names = _texture_names(t)
            if names is not None and "texture" in cols:
                i = cols.index("texture")
                arrays[i] = [names[k] if k >= 0 else "" for k in arrays[i]]
            out[f"{d.name}/{f.name}"] = (cols, sorted(zip(*arrays)) if t.num_rows else [])
        if (d / "merged.npz").exists():
            m = np.load(d / "merged.npz")
            tri = np.round(m["vertices"][m["faces"]].reshape(len(m["faces"]), -1).astype(np.float64), 4)
            out[f"{d.name}/merged"] = np.unique(tri, axis=0).tolist()
    return out

def _first_difference(got: dict, want: dict, keys: list[str]) -> str:
    """One line per differing table: its key, columns and the first differing row."""
    lines = []
    for k in keys:
        (cols, a), (_, b) = got[k], want[k]
        i = next((n for n, (x, y) in enumerate(zip(a, b)) if x != y), min(len(a), len(b)))
        lines.append(f"{k}: {len(a)} vs {len(b)} rows; row {i}: {a[i] if i < len(a) else None} vs "
                     f"{b[i] if i < len(b) else None} ({cols})")
    return "\n".join(lines)

def _recorded_textures(work: Path) -> set[str]:
    """Every texture reference the work dir records: the faces tables' metadata and the merged tiles'."""
    from storage.patches.schema import META_KEY

    refs = set()
    for f in (work / "tiles").glob("*/faces.parquet"):
        raw = (pq.read_schema(f).metadata or {}).get(META_KEY)
        refs.update(json.loads(raw).get("textures", []) if raw else [])
    for f in (work / "tiles").glob("*/merged.json"):
        refs.update(json.loads(f.read_text())["textures"])
    return refs


def _region_files(work: Path) -> dict[str, list[str]]:
    return {d.name: sorted(p.name for p in d.iterdir()) for d in sorted((work / "regions").iterdir())
            if d.is_dir() and not d.name.startswith("_")}


def test_a_commit_is_seen_whole_by_another_mirror(s3, tmp_path):
    from storage.objstore.mirror import Mirror
    from storage.objstore.store import open_store

    store = open_store(s3 + "/work")
    a = Mirror(store, tmp_path / "a")
    (a.root / "tiles" / "0_0").mkdir(parents=True)
    (a.root / "tiles" / "0_0" / "points.parquet").write_bytes(b"P" * 100)
    (a.root / "manifest.d" / "partition").mkdir(parents=True)
    (a.root / "manifest.d" / "partition" / "0_0.json").write_text("{}")
    (a.root / "tiles" / "0_0" / ".points.tmp").write_bytes(b"half")  # being written: never pushed
    rec = a.push("partition")
    assert sorted(rec.files) == ["manifest.d/partition/0_0.json", "tiles/0_0/points.parquet"]
    assert a.push() is None  # nothing changed since
    b = Mirror(store, tmp_path / "b")
    assert b.pull() == 2
    src, dst = a.root / "tiles/0_0/points.parquet", b.root / "tiles/0_0/points.parquet"
    assert dst.read_bytes() == b"P" * 100 and dst.stat().st_mtime_ns == src.stat().st_mtime_ns
    assert not (b.root / "tiles/0_0/.points.tmp").exists()
    (b.root / "manifest.d" / "partition" / "0_0.json").unlink()  # b drops the record ...
    b.push("drop")
    a.pull()
    assert not (a.root / "manifest.d/partition/0_0.json").exists()  # ... and a sees it gone
    assert (a.root / "tiles/0_0/points.parquet").exists()


def test_a_task_killed_before_its_record_leaves_nothing_trusted(s3, tmp_path, monkeypatch):
    """A scan task on S3 dies after uploading its objects, before its commit record: another process
    sees neither its outputs nor its manifest record, plans the unit to run again, and the sweep removes
    the orphans."""
    from flows.planned import pending
    from flows.remote import mirror_for
    from flows.tasks import scan_task
    from storage.objstore.commit import sweep_unrecorded
    from tasks.config import CampusConfig
    from tasks.scan import scan_files

    campus = build_campus(tmp_path / "campus")
    upload(campus.parent, s3 + "/campus")
    cfg = CampusConfig.from_yaml(campus, {"work_dir": s3 + "/work", "inputs.mesh": [s3 + "/campus/mesh"],
                                          "inputs.points": [s3 + "/campus/mls"]})
    cj = cfg.model_dump(mode="json")
    _, _, files = scan_files(cfg)
    mesh = [f for f in files if f["kind"] == "mesh"][:1]

    class Killed(BaseException):
        pass

    store = mirror_for(cfg.work_dir).store
    real_put = store.put

    def put_then_die(key, data):  # the worker dies after its objects, before the record
        if key.startswith("records/"):
            raise Killed
        return real_put(key, data)

    monkeypatch.setattr(store, "put", put_then_die)
    with pytest.raises(Killed):
        scan_task.fn(mesh, cj)
    orphans = [o.key for o in store.list("objects")]
    assert any(k.endswith(".npz") for k in orphans) and any("manifest.d/scan/" in k for k in orphans)

    fresh_process(monkeypatch, tmp_path / "cache-b")
    other = mirror_for(cfg.work_dir)
    other.pull()
    assert not list(other.root.rglob("*.npz")) and not (other.root / "manifest.d").exists()
    from storage.workdir.layout import WorkDir

    todo, done = pending(WorkDir(other.root), scan_task, mesh, "scan", cfg_json=cj)
    assert todo == mesh and not done  # nothing trusted: the unit runs again
    assert sorted(sweep_unrecorded(other.store, grace_s=0)) == sorted(orphans)
    assert scan_task.fn(mesh, cj)[0]["status"] == "done"
    fresh_process(monkeypatch, tmp_path / "cache-c")
    third = mirror_for(cfg.work_dir)
    third.pull()
    assert len(list(third.root.rglob("*.npz"))) == 1
    todo, _ = pending(WorkDir(third.root), scan_task, mesh, "scan", cfg_json=cj)
    assert todo == []  # the recorded unit is done for every process


@pytest.mark.slow
def test_tiny_campus_on_s3_equals_local_and_reruns_as_noop(tiny_campus, s3, tmp_path, monkeypatch):
    """The synth tiny campus (a ContextCapture production, COLMAP cameras and images, labels) with inputs and
    work dir on S3, inline, has the local run's stores by content and rebuilds the same regions, and reruns as
    a no-op from an empty mirror.
    Registration is off to keep it short (it gives the same transform under other names or URLs:
    tests/flows/test_reprocessing.py::test_renamed_inputs_in_another_run_order_give_the_same_stores_and_grades)."""
    from flows.campus import InlineExecutor, run_campus
    from flows.remote import DRIVER_PULL_MAX_BYTES, mirror_for
    from tasks.config import CampusConfig

    over = {"runner": "inline", "report.enabled": False, "registration.mode": "off"}
    local = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {**over, "work_dir": str(tmp_path / "local")})
    run_campus(local, executor=InlineExecutor())
    upload(tiny_campus, s3 + "/campus")
    c = s3 + "/campus"
    remote = CampusConfig.from_yaml(tiny_campus / "campus.yaml", {
        **over, "work_dir": s3 + "/work", "inputs.mesh": [c + "/mesh"], "inputs.points": [c + "/mls"],
        "inputs.labels": c + "/truth/defects.json", "inputs.images": c + "/images", "inputs.cameras": c + "/sparse/0"})
    first = run_campus(remote, executor=InlineExecutor())
    assert first["stages"]["repair"]["run"] > 0  # rebuilt regions, textured from the staged images
    refs = _recorded_textures(mirror_for(remote.work_dir).root)
    inputs = sorted(t for t in refs if t.startswith(c + "/mesh/"))  # never this process's cache paths:
    assert inputs and all(t in inputs or t.startswith("../../regions/") for t in refs), refs  # URL or work dir
    shutil.rmtree(tmp_path / "cache-a")  # the first process's copies are gone: another worker stages its own
    fresh_process(monkeypatch, tmp_path / "cache-b")
    from storage.inputs.remote import readable

    assert Path(readable(inputs[0])).is_relative_to(tmp_path / "cache-b")
    again = run_campus(remote, executor=InlineExecutor())  # another process, an empty mirror: nothing to redo
    assert all(c["run"] == 0 for c in again["stages"].values()), again["stages"]
    mirror = mirror_for(remote.work_dir)
    # the driver planned from the records: no store, staging run, merged tile or region mesh came down (but the
    # small files every pull of the driver brings: records, JSON, files of at most DRIVER_PULL_MAX_BYTES)
    held = {p.relative_to(mirror.root).as_posix(): p.stat().st_size for p in mirror.root.rglob("*") if p.is_file()}
    heavy = [r for r, n in held.items() if n > DRIVER_PULL_MAX_BYTES and
             (r.startswith("staging/") or r.endswith(("points.parquet", "faces.parquet", ".npz", ".glb")))]
    assert not heavy, heavy
    recorded = sum(size for size, _ in mirror.files.values())
    assert mirror.store.stats.bytes_read <= 0.01 * recorded, (mirror.store.stats.bytes_read, recorded)
    mirror.pull()  # now all of it, to compare
    got, want = tables_by_content(mirror.root), tables_by_content(tmp_path / "local")
    assert sorted(got) == sorted(want)  # the same tiles, stores and merged meshes
    differ = sorted(k for k in got if "merged" not in k and got[k] != want[k])
    assert not differ, _first_difference(got, want, differ)  # named, never a dict diff pytest spends minutes on
    # a rebuilt region depends on the order of its points within a patch, which follows the inputs' source
    # ids (paths vs URLs): the same regions are rebuilt and textured, not necessarily to the same triangles
    assert _region_files(mirror.root) == _region_files(tmp_path / "local")
    assert not [p for p in mirror.root.rglob("*") if p.is_file() and SECRET.encode() in p.read_bytes()]
    assert os.environ["MS3D_CACHE"] == str(tmp_path / "cache-b")

def test_compaction_keeps_the_state_and_frees_superseded_objects(s3, tmp_path):
    from storage.objstore.commit import sweep_unrecorded
    from storage.objstore.mirror import Mirror
    from storage.objstore.store import open_store

    store = open_store(s3 + "/work")
    a = Mirror(store, tmp_path / "a")
    for version in (b"v1", b"v2-longer"):  # a file rewritten: its first object is superseded
        (a.root / "tiles").mkdir(exist_ok=True)
        (a.root / "tiles" / "t.parquet").write_bytes(version)
        (a.root / f"keep-{len(version)}.json").write_text("{}")
        a.push()
    (a.root / "keep-2.json").unlink()
    a.push()
    assert a.compact() == 3 and len(store.list("records")) == 1
    assert len(sweep_unrecorded(store, grace_s=0)) == 2  # the superseded v1 object and the deleted file's
    b = Mirror(store, tmp_path / "b")
    b.pull()
    assert sorted(p.relative_to(b.root).as_posix() for p in b.root.rglob("*") if p.is_file()) == \
        ["keep-9.json", "tiles/t.parquet"]
    assert (b.root / "tiles/t.parquet").read_bytes() == b"v2-longer"


def test_a_run_that_lost_its_lease_starts_no_more_tasks(tmp_path):
    """The driver checks its lease before each stage's tasks and when it collects them: a run whose lease
    was taken over stops with LeaseLost and pushes nothing more."""
    from types import SimpleNamespace

    from flows.remote import SyncExecutor
    from storage.objstore.lock import LeaseLost

    calls = []

    class Inner:
        def map(self, tsk, batches, label, **consts):
            calls.append(label)
            return SimpleNamespace(results=lambda: [1])

        def submit(self, tsk, *args):
            calls.append(tsk.name)
            return SimpleNamespace(result=lambda: 1)

    lease = SimpleNamespace(lost=None)
    lease.check = lambda: (_ for _ in ()).throw(lease.lost) if lease.lost else None
    mirror = SimpleNamespace(lease=lease, push=lambda *a: calls.append("push"), pull=lambda only=None: calls.append("pull"),
                             release=lambda keep=None: 0)
    ex = SyncExecutor(Inner(), mirror)
    assert ex.map(SimpleNamespace(name="scan"), [[1]], "scan").results() == [1]
    assert calls == ["push", "scan", "pull"]
    pending = ex.map(SimpleNamespace(name="ingest"), [[1]], "ingest")
    one = ex.submit(SimpleNamespace(name="regions"))
    lease.lost = LeaseLost("s3://b/w: the run lock was taken over by another run")
    with pytest.raises(LeaseLost):
        pending.results()  # collected after the loss: not pulled into the driver
    with pytest.raises(LeaseLost):
        one.result()
    with pytest.raises(LeaseLost):
        ex.map(SimpleNamespace(name="partition"), [[1]], "partition")
    assert calls == ["push", "scan", "pull", "push", "ingest", "push", "regions"]  # nothing after the loss


def test_tasks_pull_what_they_read(s3, tmp_path, monkeypatch):
    """As the stages declare (``STAGE.reads`` / ``skips``): classify pulls only its tiles' stores; repair pulls everything but the ingest runs and export's
    outputs; the files it leaves in the bucket are not taken for deletions when it pushes."""
    from flows.remote import mirror_for, synced
    from storage.objstore.mirror import Mirror
    from storage.objstore.store import open_store
    from tasks.classify import STAGE as CLASSIFY
    from tasks.repair import STAGE as REPAIR

    work = s3 + "/work"
    a = Mirror(open_store(work), tmp_path / "writer")
    for rel in ("staging/1_1/run-000.arrow", "tiles/1_1/points.parquet", "tiles/2_1/points.parquet",
                "regions/plan.json", "output/tileset.json", "manifest.d/classify/1_1.json"):
        (a.root / rel).parent.mkdir(parents=True, exist_ok=True)
        (a.root / rel).write_text(rel)
    a.push("writer")
    cj = {"work_dir": work, "inputs": {}}
    seen = {}

    def classify_task(tile_keys, cfg_json):
        root = mirror_for(work).root
        seen["classify"] = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())

    def repair_task(region_keys, cfg_json):
        root = mirror_for(work).root
        seen["repair"] = sorted(p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
        (root / "regions" / "r1.npz").write_text("new")

    fresh_process(monkeypatch, tmp_path / "cache-w1")
    synced(CLASSIFY)(classify_task)(["1_1"], cj)
    assert seen["classify"] == ["manifest.d/classify/1_1.json", "tiles/1_1/points.parquet"]
    fresh_process(monkeypatch, tmp_path / "cache-w2")
    synced(REPAIR)(repair_task)(["r1"], cj)
    assert seen["repair"] == ["manifest.d/classify/1_1.json", "regions/plan.json", "tiles/1_1/points.parquet",
                              "tiles/2_1/points.parquet"]
    fresh_process(monkeypatch, tmp_path / "cache-reader")
    b = mirror_for(work)
    b.pull()
    assert (b.root / "staging/1_1/run-000.arrow").read_text() == "staging/1_1/run-000.arrow"  # not deleted
    assert (b.root / "regions/r1.npz").read_text() == "new"
