"""What a mirror's records say about files it has not downloaded (storage.recorded): states, digests, listings
and deletions equal the downloaded files', with nothing downloaded; bytes come down only when asked for."""

from __future__ import annotations

import os

import pytest

from storage import recorded
from storage.atomic import file_fingerprint, file_sha256, local_file_fingerprint
from storage.ids import TileId
from storage.objstore import mirror as mirror_module
from storage.objstore.mirror import Mirror, mirror_of
from storage.objstore.store import open_store
from storage.workdir.layout import WorkDir

FILES = {"tiles/1_1/patches.parquet": b"P" * 300, "tiles/1_1/points.parquet": b"p" * (3 << 20),
         "tiles/2_1/stale.json": b"{}", "staging/1_1/u0-000.arrow": b"s" * 500, "regions/r1/mesh.npz": b"m" * 70}


@pytest.fixture
def bucket(tmp_path, monkeypatch):
    """A store with FILES committed by another process's mirror; (store, that mirror's folder)."""
    monkeypatch.setattr(mirror_module, "_MIRRORS", {})
    monkeypatch.setattr(mirror_module, "_SWEPT", set())
    store = open_store(str(tmp_path / "bucket"))
    writer = Mirror(store, tmp_path / "writer")
    for rel, data in FILES.items():
        (writer.root / rel).parent.mkdir(parents=True, exist_ok=True)
        (writer.root / rel).write_bytes(data)
    writer.push("writer")
    return store, writer.root


def _reader(store, tmp_path, name="reader"):
    m = mirror_of(store, tmp_path / name)
    m.pull(lambda rel: False)  # the records only
    return m


def test_states_and_digests_come_from_the_records(bucket, tmp_path):
    store, src = bucket
    m = _reader(store, tmp_path)
    read0 = store.stats.bytes_read
    points, local = m.root / "tiles/1_1/points.parquet", src / "tiles/1_1/points.parquet"
    st = recorded.state(points)
    assert not points.exists() and (st.size, st.mtime_ns) == (3 << 20, local.stat().st_mtime_ns)
    assert file_sha256(points) == file_sha256(local) == st.sha256
    assert file_fingerprint(points) == local_file_fingerprint(local) == st.fingerprint
    assert recorded.exists(points) and recorded.is_dir(m.root / "tiles") and not recorded.exists(m.root / "nope")
    assert store.stats.bytes_read == read0 and not points.exists()  # nothing downloaded

    assert recorded.children(m.root / "tiles") == [m.root / "tiles/1_1", m.root / "tiles/2_1"]
    assert recorded.glob(m.root / "tiles", "*/patches.parquet") == [m.root / "tiles/1_1/patches.parquet"]
    assert recorded.glob(m.root, "**/*.npz") == [m.root / "regions/r1/mesh.npz"]
    assert recorded.glob(m.root / "staging", "*/u0-*.arrow") == [m.root / "staging/1_1/u0-000.arrow"]  # a unit's runs
    wd = WorkDir(m.root)
    assert wd.done_tiles() == wd.live_tiles() == [TileId(1, 1)] and wd.staged_tiles() == [TileId(1, 1)]
    assert wd.tile_keys_on_disk() == ["1_1", "2_1"]


def test_bytes_come_down_when_asked_and_local_changes_win(bucket, tmp_path):
    store, src = bucket
    m = _reader(store, tmp_path)
    patches = m.root / "tiles/1_1/patches.parquet"
    assert recorded.ensure_local(m.root / "tiles/1_1") == 2 and patches.read_bytes() == b"P" * 300
    assert recorded.state(patches).sha256 is not None  # the downloaded copy is the recorded file
    os.utime(patches, ns=(1, 1))
    assert recorded.state(patches).sha256 is None and file_sha256(patches) == file_sha256(src / patches.relative_to(m.root))
    assert recorded.ensure_local(m.root / "staging/1_1/u0-000.arrow") == 1
    assert recorded.ensure_local(m.root / "staging/1_1/u0-000.arrow") == 0


def test_a_deletion_before_the_download_is_published(bucket, tmp_path):
    store, _ = bucket
    m = _reader(store, tmp_path)
    recorded.unlink(m.root / "staging/1_1/u0-000.arrow")
    recorded.remove_tree(m.root / "regions")
    assert not recorded.exists(m.root / "staging/1_1/u0-000.arrow") and not recorded.is_dir(m.root / "regions")
    rec = m.push("driver")
    assert sorted(rec.meta["deleted"]) == ["regions/r1/mesh.npz", "staging/1_1/u0-000.arrow"]
    other = Mirror(store, tmp_path / "other")
    other.pull()
    assert sorted(p.relative_to(other.root).as_posix() for p in other.root.rglob("*") if p.is_file()) == \
        ["tiles/1_1/patches.parquet", "tiles/1_1/points.parquet", "tiles/2_1/stale.json"]


def test_a_lazy_mirror_keeps_what_it_wrote_before_downloading(bucket, tmp_path):
    store, _ = bucket
    m = _reader(store, tmp_path)
    m.lazy = True
    mesh = m.root / "regions/r1/mesh.npz"
    mesh.parent.mkdir(parents=True)
    mesh.write_bytes(b"newer")  # written here, the recorded version never downloaded
    m.pull()
    assert mesh.read_bytes() == b"newer"
    m.push("driver")
    other = Mirror(store, tmp_path / "other")
    other.pull()
    assert (other.root / "regions/r1/mesh.npz").read_bytes() == b"newer"


def test_a_plain_path_is_the_local_file(tmp_path):
    p = tmp_path / "a.bin"
    p.write_bytes(b"abc")
    st = recorded.state(p)
    assert (st.size, st.mtime_ns, st.sha256) == (3, p.stat().st_mtime_ns, None)
    assert recorded.state(tmp_path) is None and recorded.is_dir(tmp_path) and recorded.children(tmp_path) == [p]


def test_released_copies_stay_known_and_come_back_from_the_cache(bucket, tmp_path):
    store, _ = bucket
    m = _reader(store, tmp_path)
    assert m.pull() == len(FILES)
    changed = m.root / "tiles/2_1/stale.json"
    changed.write_text('{"error": "x"}')  # changed here, not pushed yet: kept
    assert m.release() == len(FILES) - 1
    assert sorted(p.relative_to(m.root).as_posix() for p in m.root.rglob("*") if p.is_file()) == ["tiles/2_1/stale.json"]
    assert recorded.state(m.root / "tiles/1_1/points.parquet").size == 3 << 20
    read0 = store.stats.bytes_read
    assert m.pull() == len(FILES) - 1 and m.stats["cache_hits"] == len(FILES) - 1
    assert store.stats.bytes_read - read0 < 1000  # the records' listing only: the bytes came from the cache
    rec = m.push("worker")
    assert sorted(rec.files) == ["tiles/2_1/stale.json"] and rec.meta["deleted"] == []
