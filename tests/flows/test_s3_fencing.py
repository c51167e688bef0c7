"""Commits on a bucket fenced by the run (storage.objstore.epoch, storage.objstore.mirror, flows.remote): the probes
that failed on per-process mirrors ordered by wall clocks, against moto's S3 server on 127.0.0.1.

- a superseded driver's late commit is refused, and one that slips through is read by nobody;
- a long-lived worker across two runs, with a tile deleted between them, holds no stale tile;
- a process that reuses a killed process's pid publishes nothing the killed task left behind;
- two threads of one worker each publish only what their own task wrote;
- a task killed in the middle of its batch loses at most the unit in progress.
"""

from __future__ import annotations

import threading
import uuid

import pytest

from storage.errors import InputError

BUCKET = "ms3d-fencing-test"
KEY_ID = "AKIAMS3DFENCINGKEY01"
SECRET = "ms3d-fencing-secret-DO-NOT-LOG-7c2a"


@pytest.fixture(scope="module")
def s3_server(moto_s3):
    return moto_s3(BUCKET, KEY_ID, SECRET)


@pytest.fixture
def store(s3_server, monkeypatch, tmp_path):
    """A fresh work dir prefix on the local server (its Store), a fresh cache and no mirror in memory."""
    from storage.inputs import remote as remote_inputs
    from storage.objstore import mirror as mirror_mod
    from storage.objstore.store import open_store

    for k in ("AWS_PROFILE", "AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    for k, v in {"AWS_ENDPOINT_URL": s3_server, "AWS_ACCESS_KEY_ID": KEY_ID, "AWS_SECRET_ACCESS_KEY": SECRET,
                 "AWS_DEFAULT_REGION": "us-east-1", "MS3D_CACHE": str(tmp_path / "cache")}.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setattr(remote_inputs, "_STORES", {})
    monkeypatch.setattr(mirror_mod, "_MIRRORS", {})
    return open_store(f"s3://{BUCKET}/{uuid.uuid4().hex[:10]}/work")


def _write(root, rel: str, data: bytes) -> None:
    (root / rel).parent.mkdir(parents=True, exist_ok=True)
    (root / rel).write_bytes(data)


def _files(root) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in root.rglob("*") if p.is_file()}


def _run(store, owner: str, ttl_s: float = 30.0):
    """A driver taking the work dir: its lease and its epoch (as flows.remote.remote_run does)."""
    from storage.objstore.epoch import begin_epoch
    from storage.objstore.lock import acquire_lease
    from storage.objstore.mirror import SYNC_STAGE

    lease = acquire_lease(store, owner=owner, ttl_s=ttl_s)
    keys = [i.key for i in store.list(f"records/{SYNC_STAGE}")]
    return lease, begin_epoch(store, lease.token, keys).number


def test_a_superseded_drivers_late_commit_is_refused_and_never_read(store, tmp_path):
    import json
    import time

    from storage.objstore.commit import put_unit_outputs
    from storage.objstore.epoch import record_unit
    from storage.objstore.mirror import SYNC_STAGE, Mirror, RunSuperseded

    _, epoch_a = _run(store, "run-a", ttl_s=0.5)
    a = Mirror(store, tmp_path / "a")
    a.epoch = epoch_a
    _write(a.root, "tiles/0_0/points.parquet", b"v1")
    a.push("a")
    time.sleep(0.6)  # run a's lease lapses (its driver hangs); run b takes over
    _, epoch_b = _run(store, "run-b")
    assert epoch_b == epoch_a + 1
    _write(a.root, "tiles/0_0/points.parquet", b"v2 from the superseded run")
    with pytest.raises(RunSuperseded, match="a later ms3d run has begun"):
        a.push("a, late")  # its task learns it before committing ...
    late = put_unit_outputs(store, SYNC_STAGE, record_unit(epoch_a, 99, "late"),  # ... and one that raced past
                            {"tiles/0_0/points.parquet": b"v2 from the superseded run"},
                            {"mtime_ns": {"tiles/0_0/points.parquet": time.time_ns()}, "deleted": []})
    assert store.exists(f"records/{SYNC_STAGE}/{late.unit}.json")
    reader = Mirror(store, tmp_path / "reader")
    reader.pull()
    assert _files(reader.root) == {"tiles/0_0/points.parquet": b"v1"}  # the late commit is read by nobody
    epochs = sorted(i.key for i in store.list("epochs"))
    assert len(epochs) == 2 and json.loads(store.get(epochs[-1]))["epoch"] == epoch_b


def test_a_long_lived_worker_holds_no_tile_the_next_run_deleted(store, tmp_path):
    from storage.objstore.mirror import Mirror

    _, e1 = _run(store, "run-1")
    driver = Mirror(store, tmp_path / "driver")
    driver.epoch = e1
    for t in ("0_0", "1_0"):
        _write(driver.root, f"tiles/{t}/points.parquet", t.encode())
    driver.push("run 1")
    worker = Mirror(store, tmp_path / "worker")  # a worker process that lives on
    worker.epoch = e1
    worker.pull()
    assert set(_files(worker.root)) == {"tiles/0_0/points.parquet", "tiles/1_0/points.parquet"}
    store.delete([".lock.json"])  # run 1 ended
    _, e2 = _run(store, "run-2")
    d2 = Mirror(store, tmp_path / "driver2")
    d2.epoch = e2
    d2.pull()
    (d2.root / "tiles/1_0/points.parquet").unlink()  # the plan no longer names tile 1_0
    d2.push("run 2: prune")
    d2.compact()  # the records the worker folded are gone; one state record stands for them
    worker.epoch = e2  # its next task is one of run 2
    worker.pull()
    assert set(_files(worker.root)) == {"tiles/0_0/points.parquet"}


def test_a_process_reusing_a_killed_processs_pid_publishes_nothing_it_left(store, tmp_path, monkeypatch):
    from storage.objstore import mirror as mirror_mod

    cache = tmp_path / "cache"
    killed = mirror_mod.mirror_of(store, cache)
    _write(killed.root, "tiles/9_9/points.parquet", b"written by a task that was killed before its push")
    monkeypatch.setattr(mirror_mod, "_MIRRORS", {})  # the process is gone ...
    monkeypatch.setattr(mirror_mod, "_SWEPT", set())
    monkeypatch.setattr(mirror_mod, "_INSTANCE", "restarted")  # ... and another one has the same pid
    fresh = mirror_mod.mirror_of(store, cache)
    assert fresh.root != killed.root and not killed.root.exists()  # the leftover folder is swept
    assert fresh.push("restarted") is None and not store.list("records")


def test_two_threads_of_a_worker_publish_only_their_own_tasks_files(store, tmp_path):
    from storage.objstore import mirror as mirror_mod

    cache, barrier, out = tmp_path / "cache", threading.Barrier(2), {}

    def task(tile: str) -> None:
        m = mirror_mod.mirror_of(store, cache)
        _write(m.root, f"tiles/{tile}/points.parquet", tile.encode())
        barrier.wait()  # both tasks have written before either publishes
        out[tile] = sorted(m.push(tile).files)

    threads = [threading.Thread(target=task, args=(t,)) for t in ("0_0", "1_0")]
    [t.start() for t in threads]
    [t.join() for t in threads]
    assert out == {"0_0": ["tiles/0_0/points.parquet"], "1_0": ["tiles/1_0/points.parquet"]}


def test_a_task_killed_mid_batch_loses_at_most_the_unit_in_progress(store, tmp_path, monkeypatch):
    from flows.remote import mirror_for, synced
    from storage.objstore import mirror as mirror_mod
    from storage.workdir.layout import WorkDir
    from tasks.stages import StageSpec
    from tasks.units import Done, run_unit

    class Killed(BaseException):
        pass

    work = store.url
    _, epoch = _run(store, "run-k")

    def batch_task(tiles: list[str], cfg_json: dict) -> list[dict]:
        wd = WorkDir(mirror_for(cfg_json["work_dir"]).root)
        out = []
        for t in tiles:
            def work(t=t):
                if t == "2_0":
                    raise Killed  # the worker dies in the third unit
                _write(wd.root, f"tiles/{t}/merged.npz", t.encode())
                return Done(outputs=[f"tiles/{t}/merged.npz"])
            out.append(run_unit(wd, "merge", t, "fp", {}, work))
        return out

    task = synced(StageSpec("merge", "tile", reads=("tiles/{tile}/",)))(batch_task)
    with pytest.raises(Killed):
        task(["0_0", "1_0", "2_0", "3_0"], {"work_dir": work, "inputs": {}, "_ms3d_run_epoch": epoch})
    monkeypatch.setattr(mirror_mod, "_MIRRORS", {})  # another process looks at the bucket
    reader = mirror_mod.Mirror(store, tmp_path / "reader")
    reader.pull()
    assert sorted(p for p in _files(reader.root) if p.endswith(".npz")) == \
        ["tiles/0_0/merged.npz", "tiles/1_0/merged.npz"]  # the two finished units are committed
    assert sorted(p.name for p in (reader.root / "manifest.d" / "merge").glob("*.json")) == ["0_0.json", "1_0.json"]


def test_an_epoch_is_taken_by_one_run_only(store):
    from storage.objstore.epoch import begin_epoch, epoch_key
    from storage.objstore.store import PreconditionFailed

    first = begin_epoch(store, "token-a", [])
    with pytest.raises(PreconditionFailed):
        store.put_if_absent(epoch_key(first.number), b"{}")  # the create that numbered it cannot be repeated
    assert begin_epoch(store, "token-b", []).number == first.number + 1
    with pytest.raises(InputError, match="not a valid run epoch"):
        store.put(epoch_key(first.number + 2), b"garbage")
        from storage.objstore.epoch import latest_epoch

        latest_epoch(store)


def test_concurrent_downloads_count_exactly_and_a_missing_object_stays_pending(store, tmp_path, monkeypatch):
    """A pull downloads its files several at a time (storage.objstore.pool): the same bytes and request counts as
    one at a time; an object gone from the bucket fails alone, names itself, and is tried again by a later read."""
    from storage.objstore.mirror import Mirror

    writer = Mirror(store, tmp_path / "w")
    for i in range(24):
        _write(writer.root, f"tiles/{i}_0/points.parquet", bytes([i]) * (1000 + i))
    rec = writer.push("writer")
    counts = {}
    for threads in ("1", "8"):
        monkeypatch.setenv("MS3D_IO_THREADS", threads)
        reader, before = Mirror(store, tmp_path / f"r{threads}"), store.stats.requests["GetObject"]
        assert reader.pull() == 24
        assert _files(reader.root) == _files(writer.root)
        counts[threads] = store.stats.requests["GetObject"] - before
    assert counts["1"] == counts["8"]

    lost = rec.files["tiles/5_0/points.parquet"].key
    store.delete([lost])
    reader = Mirror(store, tmp_path / "r-lost")
    with pytest.raises(InputError, match="5_0/points.parquet.*missing"):
        reader.pull()
    assert len(_files(reader.root)) == 23  # every other file came in
    assert reader.pending_under("tiles/5_0") == ["tiles/5_0/points.parquet"]
    with pytest.raises(InputError, match="missing"):
        reader.fetch(["tiles/5_0/points.parquet"])


def test_a_region_reads_its_patches_by_byte_ranges_and_a_busy_tile_whole(store, tmp_path, monkeypatch):
    """On a bucket a repair region opens a tile's tables over ranged GETs (storage.patches.remote_read): the
    patches equal a local read, far fewer bytes than the tables come over, nothing lands on scratch; once half a
    table came by ranges, the next open downloads it whole instead."""
    import numpy as np

    from storage.objstore.mirror import Mirror
    from storage.patches import remote_read
    from storage.patches.read import PatchStore
    from storage.patches.schema import POINTS_FILE
    from storage.patches.write import write_tile_tables
    from tests.storage.patches.test_patch_store import META, _tile

    monkeypatch.setenv("MS3D_RANGED_SHARE", "0.5")  # off by default (docs/benchmarks.md)
    writer = Mirror(store, tmp_path / "w")
    P, F, T = _tile(n=60_000, m=6_000, seed=3)
    write_tile_tables(writer.root / "tiles" / "3_-2", P, F, T, META, row_group_size=2_000)
    writer.push("partition")
    local = PatchStore(writer.root / "tiles" / "3_-2")
    keys = local.patches()["patch"]

    reader = Mirror(store, tmp_path / "r")
    reader.pull(only=lambda rel: False)  # the records only: nothing downloaded
    from storage import recorded

    recorded.register(reader)
    try:
        tile = reader.root / "tiles" / "3_-2"
        size = (writer.root / "tiles" / "3_-2" / POINTS_FILE).stat().st_size
        before = store.stats.bytes_read
        ranged = remote_read.open_for_patches(tile)
        got = ranged.read_patches(keys[:3].tolist())
        want = local.read_patches(keys[:3].tolist())
        assert all(np.array_equal(g.points["x"], w.points["x"]) and np.array_equal(g.faces["vid0"], w.faces["vid0"])
                   for g, w in zip(got, want))
        assert store.stats.bytes_read - before < 0.5 * size
        assert not (tile / POINTS_FILE).exists()  # read in place, not downloaded
        ranged.read_patches(keys.tolist())  # the whole tile by ranges: past half of it
        assert remote_read.fetched_by_range(recorded.remote_object(tile / POINTS_FILE)[1]) >= 0.5 * size
        remote_read.open_for_patches(tile).read_patches(keys[:1].tolist())
        assert (tile / POINTS_FILE).exists()  # this time the table came whole (and is read locally)
    finally:
        recorded.unregister(reader.root)
    # a table the node's cache holds whole is copied from it, never fetched by ranges
    from storage.objstore.cas import content_cache

    node = Mirror(store, tmp_path / "r2")
    node.cas = content_cache(tmp_path / "node" / "objects")
    node.pull(only=lambda rel: False)
    rel = "tiles/3_-2/" + POINTS_FILE
    assert node.object_of(rel) is not None
    node.fetch([rel])  # another task of this node read it whole: now in the cache
    node2 = Mirror(store, tmp_path / "r3")
    node2.cas = node.cas
    node2.pull(only=lambda rel: False)
    assert node2.object_of(rel) is None
