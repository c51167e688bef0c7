"""Per-process I/O figures (storage.objstore.iostats): one file per process instance under its cache folder,
cumulative, equal to what the process's stores, mirrors and content cache counted."""

from __future__ import annotations

import json
import os

import pytest

from storage.objstore import cas as cas_module
from storage.objstore import mirror as mirror_module
from storage.objstore.iostats import io_stats_path, read_io_stats, write_io_stats
from storage.objstore.mirror import Mirror, mirror_of, process_instance
from storage.objstore.store import open_store

from .test_objstore import s3_env, s3_server, s3_store  # noqa: F401 - fixtures


@pytest.fixture
def fresh_process(monkeypatch):
    """No mirror, content cache, input store or figure noted yet, as in a new process."""
    from storage.inputs import remote as remote_inputs
    from storage.objstore import iostats

    monkeypatch.setattr(iostats, "_ROLES", set())
    monkeypatch.setattr(iostats, "_TASKS", {})
    monkeypatch.setattr(mirror_module, "_MIRRORS", {})
    monkeypatch.setattr(mirror_module, "_SWEPT", set())
    monkeypatch.setattr(cas_module, "_CACHES", {})
    monkeypatch.setattr(remote_inputs, "_STORES", {})


def _publish(store, root, files: dict[str, bytes]) -> None:
    writer = Mirror(store, root)  # another process: not this one's mirror, its I/O is not counted here
    for rel, data in files.items():
        (writer.root / rel).parent.mkdir(parents=True, exist_ok=True)
        (writer.root / rel).write_bytes(data)
    writer.push("writer")


def test_figures_are_this_process_cumulative_ones(s3_store, tmp_path, fresh_process):  # noqa: F811
    _publish(s3_store, tmp_path / "w1", {"tiles/a.bin": b"a" * 5000, "tiles/b.bin": b"b" * 3000})
    cache = tmp_path / "cache"
    reader = mirror_of(open_store(s3_store.url), cache)
    assert reader.pull() == 2

    path = write_io_stats(cache, "worker")
    assert path == io_stats_path(cache) == cache / "io-stats" / f"{os.getpid()}-{process_instance()}.json"
    doc = json.loads(path.read_text())
    st = reader.store.stats
    assert doc["pid"] == os.getpid() and doc["roles"] == ["worker"]
    assert doc["work_dir"]["bytes_read"] == st.bytes_read >= 8000
    assert doc["work_dir"]["n_requests"] == st.n_requests == sum(doc["work_dir"]["requests"].values())
    assert doc["work_dir"]["requests"]["GetObject"] == 3  # the record and its two objects
    assert doc["inputs"]["n_requests"] == 0 and doc["total"]["bytes_read"] == st.bytes_read
    assert doc["mirror"]["pulled_files"] == 2 and doc["cas"] == {"hits": 0, "misses": 2, "bytes_fetched": 8000,
                                                                 "evicted": 0}

    _publish(s3_store, tmp_path / "w2", {"tiles/c.bin": b"c" * 1000})
    assert reader.pull() == 1
    again = json.loads(write_io_stats(cache, "driver").read_text())
    assert again["roles"] == ["driver", "worker"]  # one process, both roles: one file
    assert again["work_dir"]["bytes_read"] == reader.store.stats.bytes_read >= doc["work_dir"]["bytes_read"] + 1000
    assert again["mirror"]["pulled_files"] == 3 and again["cas"]["bytes_fetched"] == 9000
    assert read_io_stats(cache) == [again]
    assert not [p for p in (cache / "io-stats").iterdir() if p.name.startswith(".")]  # no temporary left


def test_a_store_shared_by_two_mirrors_counts_once(tmp_path, fresh_process):
    import threading

    store = open_store(str(tmp_path / "bucket"))
    _publish(store, tmp_path / "w", {"x.bin": b"x" * 700})
    cache = tmp_path / "cache"
    mirrors = [mirror_of(store, cache)]
    t = threading.Thread(target=lambda: mirrors.append(mirror_of(store, cache)))  # a second thread's mirror
    t.start()
    t.join()
    assert len({id(m) for m in mirrors}) == 2 and mirrors[0].store is mirrors[1].store
    for m in mirrors:
        m.pull()
    doc = json.loads(write_io_stats(cache, "worker").read_text())
    assert doc["work_dir"]["bytes_read"] == store.stats.bytes_read
    assert doc["mirror"]["pulled_files"] == 2 and doc["cas"]["misses"] == 1 and doc["cas"]["hits"] == 1


def test_a_task_meter_splits_the_figures_by_task(tmp_path, fresh_process):
    from storage.objstore.iostats import TaskMeter

    store = open_store(str(tmp_path / "bucket"))
    _publish(store, tmp_path / "w", {"a.bin": b"a" * 400, "b.bin": b"b" * 600})
    m = mirror_of(store, tmp_path / "cache")
    with TaskMeter("merge_task") as meter:
        meter.timed("pull", m.pull, lambda rel: rel == "a.bin")
    with pytest.raises(RuntimeError), TaskMeter("merge_task") as meter:
        meter.timed("pull", m.pull)
        raise RuntimeError("a task that fails still counts")
    doc = json.loads(write_io_stats(tmp_path / "cache", "worker").read_text())
    task = doc["tasks"]["merge_task"]
    assert task["runs"] == 2 and task["bytes_read"] == store.stats.bytes_read == doc["work_dir"]["bytes_read"]
    assert task["bytes_read"] >= 1000 and 0 < task["pull_s"] <= task["seconds"] and task["push_s"] == 0
