"""The object-store layer (storage.objstore.store*) against a real S3 HTTP server: moto's server mode on
127.0.0.1, one per session, a fresh bucket prefix per test."""

from __future__ import annotations

import json
import logging
import time
import uuid

import numpy as np
import pytest

from storage.errors import InputError
from storage.grid import PatchGrid
from storage.objstore.commit import put_unit_outputs, read_output, resolve, sweep_unrecorded
from storage.objstore.lock import LOCK_KEY, Lease, LeaseLost, _Renewer, acquire_lease, run_lock
from storage.objstore.store import PreconditionFailed, open_store, redact
from storage.patches.ranges import open_ranged, read_patch_rows
from storage.patches.read import PatchStore
from storage.patches.schema import TileMeta
from storage.patches.write import write_tile_tables
from tasks.partition.kernels import build_tile_tables

BUCKET = "ms3d-test"
KEY_ID = "AKIAMS3DTESTKEY00001"
SECRET = "ms3d-secret-DO-NOT-LOG-7f3a9c"


@pytest.fixture(scope="session")
def s3_server(moto_s3):
    """The session's moto S3 server on 127.0.0.1 with this module's bucket; yields the endpoint URL."""
    return moto_s3(BUCKET, KEY_ID, SECRET)


@pytest.fixture
def s3_env(s3_server, monkeypatch):
    """The standard AWS environment pointing at the local server, for this test only."""
    for k in ("AWS_PROFILE", "AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    monkeypatch.setenv("AWS_ENDPOINT_URL", s3_server)
    monkeypatch.setenv("AWS_ACCESS_KEY_ID", KEY_ID)
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", SECRET)
    monkeypatch.setenv("AWS_DEFAULT_REGION", "us-east-1")
    return s3_server


@pytest.fixture
def s3_store(s3_env):
    return open_store(f"s3://{BUCKET}/{uuid.uuid4().hex[:12]}/work")


@pytest.fixture(params=["local", "s3"])
def any_store(request, tmp_path):
    if request.param == "local":
        return open_store(f"file://{tmp_path}/work")
    return request.getfixturevalue("s3_store")


def test_round_trip_local_and_s3(any_store, tmp_path):
    s = any_store
    s.put("a/b.bin", b"0123456789")
    s.put("a/c/d.json", b"{}")
    assert s.get("a/b.bin") == b"0123456789"
    assert s.get_range("a/b.bin", 3, 7) == b"3456"
    assert s.size("a/b.bin") == 10 and s.exists("a/c/d.json") and not s.exists("a/nope")
    assert [o.key for o in s.list("a")] == ["a/b.bin", "a/c/d.json"]
    assert [o.size for o in s.list("")] == [10, 2]
    with pytest.raises(FileNotFoundError):
        s.get("a/nope")
    with pytest.raises(ValueError):
        s.put("../escape", b"x")
    s.delete(["a/b.bin", "a/absent"])
    assert [o.key for o in s.list("")] == ["a/c/d.json"]
    record = put_unit_outputs(s, "partition", "3_-2", {"points.parquet": b"P" * 100, "meta/x.json": b"{}"},
                              meta={"fingerprint": "f00d", "params_hash": "beef"})
    again = resolve(s, "partition", "3_-2")
    assert again == record and again.meta == {"fingerprint": "f00d", "params_hash": "beef"}
    assert read_output(s, again, "points.parquet") == b"P" * 100
    staged = s.get_file(again.files["points.parquet"].key, tmp_path / "staged" / "points.parquet")
    assert staged.read_bytes() == b"P" * 100
    with pytest.raises(InputError, match="unsupported storage scheme"):
        open_store("gs://bucket/x")


def test_conditional_writes_on_s3(s3_store):
    s = s3_store
    e1 = s.put_if_absent("k", b"1")
    with pytest.raises(PreconditionFailed):
        s.put_if_absent("k", b"2")
    assert s.get_with_etag("k") == (b"1", e1)
    e2 = s.put_if_match("k", b"3", e1)
    with pytest.raises(PreconditionFailed):  # a stale etag loses
        s.put_if_match("k", b"4", e1)
    assert not s.delete_if_match("k", e1) and s.delete_if_match("k", e2)
    assert s.get_with_etag("k") is None


def test_killed_unit_leaves_nothing_trusted_and_is_swept(any_store):
    s = any_store
    done = put_unit_outputs(s, "partition", "0_0", {"points.parquet": b"good"})

    class Killed(BaseException):
        pass

    real_put = s.put

    def put_then_die(key, data):  # the process dies after the objects, before the record
        if key.startswith("records/"):
            raise Killed
        return real_put(key, data)

    s.put = put_then_die
    for unit in ("0_0", "1_0"):  # a re-run of a committed unit, and a first run
        with pytest.raises(Killed):
            put_unit_outputs(s, "partition", unit, {"points.parquet": b"half", "faces.parquet": b"half"})
    del s.put
    orphans = [o.key for o in s.list("objects") if o.key not in {r.key for r in done.files.values()}]
    assert len(orphans) == 4  # the bytes are there...
    assert resolve(s, "partition", "1_0") is None  # ...but nothing names them
    assert resolve(s, "partition", "0_0") == done
    assert read_output(s, resolve(s, "partition", "0_0"), "points.parquet") == b"good"
    assert sweep_unrecorded(s, grace_s=3600) == []  # a unit writing right now is not swept
    assert sorted(sweep_unrecorded(s, grace_s=0, now=time.time() + 5)) == sorted(orphans)
    assert [o.key for o in s.list("objects")] == [done.files["points.parquet"].key]
    put_unit_outputs(s, "partition", "1_0", {"points.parquet": b"rerun"})  # the next run commits it
    assert read_output(s, resolve(s, "partition", "1_0"), "points.parquet") == b"rerun"


def test_resolve_rejects_a_tampered_output(s3_store):
    rec = put_unit_outputs(s3_store, "merge", "0_0", {"merged.glb": b"abc"})
    s3_store.put(rec.files["merged.glb"].key, b"abd")
    with pytest.raises(InputError, match="does not match its record"):
        read_output(s3_store, rec, "merged.glb")


def test_lock_is_exclusive_renews_and_expires(s3_store):
    t0 = 1_000_000.0
    a = acquire_lease(s3_store, owner="run-a", ttl_s=30, now=t0)
    with pytest.raises(InputError, match="in use by another ms3d run .run-a"):
        acquire_lease(s3_store, owner="run-b", ttl_s=30, now=t0 + 10)
    a.renew(now=t0 + 20)  # now valid until t0 + 50
    with pytest.raises(InputError, match="in use"):
        acquire_lease(s3_store, owner="run-b", ttl_s=30, now=t0 + 40)
    # run-a crashes: no more renewals; after its expiry run-b takes over...
    b = acquire_lease(s3_store, owner="run-b", ttl_s=30, now=t0 + 51)
    assert json.loads(s3_store.get(LOCK_KEY))["owner"] == "run-b"
    with pytest.raises(LeaseLost):  # ...and a late renewal of run-a fails: it must stop
        a.renew(now=t0 + 52)
    assert not a.release()  # nor can it delete run-b's lease
    assert b.release() and not s3_store.exists(LOCK_KEY)
    with run_lock(s3_store, owner="run-c", ttl_s=0.3) as lease:  # background renewal keeps it alive
        time.sleep(0.5)
        lease.check()
        with pytest.raises(InputError, match="run-c"):
            acquire_lease(s3_store, owner="run-d", ttl_s=30)
    assert not s3_store.exists(LOCK_KEY)


def _flaky_put_if_match(store, monkeypatch, fail_calls, land_first=False):
    """Make the store's put_if_match raise a transient InputError on the given call numbers (1-based);
    with ``land_first`` the write reaches the server before the error (a lost response)."""
    real, calls = store.put_if_match, []

    def flaky(key, data, etag):
        calls.append(key)
        if len(calls) in fail_calls:
            if land_first:
                real(key, data, etag)
            raise InputError(f"{store.describe()}: {key}", "cannot write (ConnectionResetError: reset by peer)")
        return real(key, data, etag)
    monkeypatch.setattr(store, "put_if_match", flaky)
    return calls


@pytest.mark.parametrize("land_first", [False, True])
def test_renewal_survives_one_transient_error(s3_store, monkeypatch, land_first):
    # a TTL with room for a loaded machine: the first request to a fresh moto server can take a second
    lease = acquire_lease(s3_store, owner="run-t", ttl_s=6.0)
    first_expiry = lease.expires_utc
    calls = _flaky_put_if_match(s3_store, monkeypatch, {1}, land_first)
    renewer = _Renewer(lease)
    renewer.start()  # the first renewal (at 2 s) fails; the retry (0.2 s later) succeeds
    deadline = time.time() + 10
    while lease.expires_utc == first_expiry and renewer.is_alive() and time.time() < deadline:
        time.sleep(0.05)
    renewer.stop_event.set()
    renewer.join()
    assert renewer.transient_failures == 1 and len(calls) >= 2
    assert renewer.error is None and lease.lost is None
    lease.check()
    assert json.loads(s3_store.get(LOCK_KEY))["token"] == lease.token
    assert lease.expires_utc > time.time()  # renewed after the failure
    assert lease.release() and not s3_store.exists(LOCK_KEY)


def test_renewal_gives_up_near_expiry_and_takeover_is_lost_at_once(s3_store, monkeypatch):
    lease = acquire_lease(s3_store, owner="run-u", ttl_s=1.5)
    _flaky_put_if_match(s3_store, monkeypatch, set(range(1, 1000)))  # the network never comes back
    renewer = _Renewer(lease)
    renewer.start()
    renewer.join(timeout=10)
    gave_up = time.time()
    assert isinstance(lease.lost, InputError) and not isinstance(lease.lost, LeaseLost)
    assert renewer.transient_failures >= 1  # retried after the first failure (how many fit depends on the load)...
    # a renewer that gave up at its first failure would fail the time check below
    assert gave_up >= lease.expires_utc - 0.25 * 1.5 - 0.01  # ...until a quarter of the TTL was left
    monkeypatch.undo()
    lease = acquire_lease(s3_store, owner="run-v", ttl_s=0.6, now=time.time() + 5)  # took over
    old = Lease(s3_store, "run-u", "not-ours", 0.6, "\"stale\"", 0.0)
    renewer = _Renewer(old)
    renewer.start()
    renewer.join(timeout=5)
    assert isinstance(old.lost, LeaseLost) and renewer.transient_failures == 0
    assert lease.release()


def test_local_lock_is_still_flock(tmp_path):
    store = open_store(tmp_path / "work")
    with run_lock(store) as lease:
        assert lease is None and (tmp_path / "work" / ".lock").exists()
        with pytest.raises(InputError, match="in use by another ms3d run"), run_lock(store):
            pass


def _tile_tables(n_patches=12, per_patch=3000, seed=0):
    size = (2.3, 1.0, 0.7)
    grid, origin = PatchGrid(size, 100.0), (0.0, 0.0, 0.0)  # cells of the world-anchored grid
    rng = np.random.default_rng(seed)
    cell = np.repeat(np.arange(n_patches), per_patch)
    xyz = rng.random((len(cell), 3)) * [2.2, 0.9, 0.6] + 0.05
    xyz[:, 0] += cell * size[0]  # one row of cells along x
    points = {"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
              "z": xyz[:, 2].astype(np.float32), "gps_time": rng.random(len(cell)) * 1e3,
              "intensity": rng.integers(0, 65535, len(cell)).astype(np.uint16)}
    p, f, patches = build_tile_tables(points, None, grid, origin)
    return p, f, patches, TileMeta(tile="0_0", patch_size_m=size)


def _upload_tile(store, tile_dir, tile_key):
    for path in sorted(tile_dir.iterdir()):
        store.put_file(f"tiles/{tile_key}/{path.name}", path)


def test_one_patch_is_read_by_byte_ranges(s3_store, tmp_path):
    p, f, patches, meta = _tile_tables()
    write_tile_tables(tmp_path / "0_0", p, f, patches, meta, row_group_size=3000)
    _upload_tile(s3_store, tmp_path / "0_0", "0_0")
    local = PatchStore(tmp_path / "0_0")
    key = int(patches["patch"][5])
    got = read_patch_rows(s3_store, "0_0", key)
    want = local.read_patch(key)
    assert got.row_groups_read <= 2 and got.columns["x"].size == want.n_points == 3000
    for c, v in want.points.items():
        np.testing.assert_array_equal(got.columns[c], v)
    assert got.bytes_fetched < got.file_size / 3, (got.bytes_fetched, got.file_size)
    with pytest.raises(KeyError):
        read_patch_rows(s3_store, "0_0", key + 10**9)


def test_laz_is_read_by_ranges(s3_store, tmp_path):
    import laspy

    n = 200_000
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [0.0] * 3
    las = laspy.LasData(header)
    rng = np.random.default_rng(2)
    las.x, las.y, las.z = rng.random(n) * 100, rng.random(n) * 100, rng.random(n) * 10
    las.write(tmp_path / "mls.laz")
    s3_store.put_file("inputs/mls.laz", tmp_path / "mls.laz")
    f = open_ranged(s3_store, "inputs/mls.laz")
    with laspy.open(f) as reader:
        assert reader.header.point_count == n
        first = next(reader.chunk_iterator(20_000))
    np.testing.assert_array_equal(first.X, las.X[:20_000])
    assert f.raw.bytes_fetched < f.raw.size / 3, (f.raw.bytes_fetched, f.raw.size)


def test_secrets_never_in_repr_errors_or_logs(s3_env, caplog):
    caplog.set_level(logging.DEBUG)  # botocore logs every signed request at DEBUG
    explicit = open_store(f"s3://{BUCKET}/x", {"key": KEY_ID, "secret": SECRET, "endpoint_url": s3_env})
    texts = [repr(explicit), explicit.describe(), repr(open_store(f"s3://{BUCKET}/y"))]
    explicit.put("k", b"1")
    errors = []
    for call in (lambda: open_store("s3://no-such-bucket-ms3d/p").put("k", b"1"),
                 lambda: open_store(f"s3://{KEY_ID}:{SECRET}@{BUCKET}/p"),
                 lambda: open_store(f"s3://{BUCKET}/p", {"password": SECRET}),
                 lambda: open_store("s3://no-such-bucket-ms3d/p", {"secret": SECRET, "key": KEY_ID}).put("k", b"")):
        with pytest.raises(InputError) as info:
            call()
        errors.append(str(info.value))
    assert "no-such-bucket-ms3d" in errors[0] and "credentials in the URL" in errors[1]
    everything = "\n".join(texts + errors) + caplog.text
    assert "Sending http request" in caplog.text  # the DEBUG request log was captured, and redacted
    assert SECRET not in everything and KEY_ID not in everything
    assert redact(f"https://h/k?X-Amz-Credential={KEY_ID}%2F&X-Amz-Signature=deadbeef") == \
        "https://h/k?X-Amz-Credential=***&X-Amz-Signature=***"


def test_an_endpoint_that_ignores_conditional_writes_is_refused_before_a_lease(s3_store, monkeypatch):
    from storage.objstore import honest

    monkeypatch.setattr(honest, "_CHECKED", {})
    honest.check_conditional_writes(s3_store)  # moto honours If-None-Match and If-Match
    assert not [o for o in s3_store.list("") if o.key.startswith(honest.PROBE_PREFIX)]  # the probe is gone
    monkeypatch.setattr(honest, "_CHECKED", {})
    real = s3_store._put_object
    monkeypatch.setattr(s3_store, "_put_object", lambda key, data, **cond: real(key, data))  # a gateway that drops them
    with pytest.raises(InputError, match="does not honour conditional writes .a second create-if-absent") as e:
        acquire_lease(s3_store, owner="run-x", ttl_s=30)
    assert "\n" not in str(e.value) and not s3_store.exists(LOCK_KEY)
