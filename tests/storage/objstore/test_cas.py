"""The node-local content-addressed cache (storage.objstore.cas) and the mirror's downloads through it."""

from __future__ import annotations

import hashlib
import threading

import pytest

from storage.objstore.cas import ContentCache


def _obj(data: bytes):
    return hashlib.sha256(data).hexdigest(), len(data)


def test_miss_then_hit_copies_and_counts(tmp_path):
    data = b"tile bytes" * 100
    sha, size = _obj(data)
    cache, fetched = ContentCache(tmp_path / "c", max_bytes=10_000_000), []

    def fetch(tmp):
        fetched.append(1)
        tmp.write_bytes(data)

    assert cache.materialise(sha, size, fetch, tmp_path / "a" / "x.bin") is False
    assert cache.materialise(sha, size, fetch, tmp_path / "b" / "x.bin") is True
    assert len(fetched) == 1
    assert (tmp_path / "a" / "x.bin").read_bytes() == data == (tmp_path / "b" / "x.bin").read_bytes()
    # a private copy: rewriting it in place leaves the cache intact
    (tmp_path / "a" / "x.bin").write_bytes(b"changed")
    cache.materialise(sha, size, fetch, tmp_path / "c.bin")
    assert (tmp_path / "c.bin").read_bytes() == data
    assert cache.stats["hits"] == 2 and cache.stats["misses"] == 1 and cache.stats["bytes_fetched"] == size


def test_survives_a_new_process_instance(tmp_path):
    data = b"immutable"
    sha, size = _obj(data)
    ContentCache(tmp_path / "c").materialise(sha, size, lambda t: t.write_bytes(data), tmp_path / "1")
    again = ContentCache(tmp_path / "c")  # a restarted process
    assert again.materialise(sha, size, lambda t: pytest.fail("downloaded again"), tmp_path / "2") is True


def test_wrong_bytes_are_refused_and_not_cached(tmp_path):
    sha, size = _obj(b"expected")
    cache = ContentCache(tmp_path / "c")
    with pytest.raises(ValueError, match="does not match"):
        cache.materialise(sha, size, lambda t: t.write_bytes(b"tampered"), tmp_path / "x")
    assert not (tmp_path / "x").exists() and cache.held_bytes() == 0


def test_bounded_least_recently_used_go_first(tmp_path):
    cache = ContentCache(tmp_path / "c", max_bytes=2500)
    blobs = [bytes([i]) * 1000 for i in range(4)]
    for i, b in enumerate(blobs):
        sha, size = _obj(b)
        cache.materialise(sha, size, lambda t, b=b: t.write_bytes(b), tmp_path / f"d{i}")
    assert cache.held_bytes() <= 2500
    newest = cache.path_of(_obj(blobs[-1])[0])
    assert newest.exists()  # the one just used stays
    assert not cache.path_of(_obj(blobs[0])[0]).exists()


def test_threads_fetch_an_object_once(tmp_path):
    data = b"shared" * 1000
    sha, size = _obj(data)
    cache, calls, lock = ContentCache(tmp_path / "c"), [], threading.Lock()

    def fetch(tmp):
        with lock:
            calls.append(1)
        tmp.write_bytes(data)

    ts = [threading.Thread(target=cache.materialise, args=(sha, size, fetch, tmp_path / f"t{i}")) for i in range(6)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert len(calls) == 1
    assert all((tmp_path / f"t{i}").read_bytes() == data for i in range(6))


def test_a_second_mirror_on_the_node_reads_nothing_again(tmp_path):
    """A new driver (a new Mirror on the same node cache) pulls the recorded state from the cache: no object
    is downloaded twice; the store's bytes read stay those of the first pull."""
    from storage.objstore.cas import content_cache
    from storage.objstore.mirror import Mirror
    from storage.objstore.store import open_store

    store = open_store(str(tmp_path / "bucket"))
    first = Mirror(store, tmp_path / "m1")
    for i in range(3):
        (first.root / f"tiles/t{i}.bin").parent.mkdir(parents=True, exist_ok=True)
        (first.root / f"tiles/t{i}.bin").write_bytes(bytes([i]) * 5000)
    first.push("writer")
    cas = content_cache(tmp_path / "node" / "objects")
    a, b = Mirror(store, tmp_path / "m2"), Mirror(store, tmp_path / "m3")
    a.cas = b.cas = cas
    read0 = store.stats.bytes_read
    assert a.pull() == 3
    read1 = store.stats.bytes_read
    assert read1 - read0 >= 15000
    assert b.pull() == 3 and b.stats["cache_hits"] == 3
    assert store.stats.bytes_read - read1 < 5000  # only the records were read again
    assert {p.name: p.read_bytes() for p in (tmp_path / "m3" / "tiles").iterdir()} == \
        {p.name: p.read_bytes() for p in (tmp_path / "m1" / "tiles").iterdir()}
