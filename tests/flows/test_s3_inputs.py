"""Inputs named by URL (storage.inputs.remote, flows.remote) against moto's S3 server on 127.0.0.1:
fingerprints from ETag + size without a download, staging once per content, discovery of a folder URL,
one clear line for a missing URL, and a config whose inputs are URLs kept as written."""

from __future__ import annotations

import os
import uuid
from pathlib import Path

import pytest

from storage.errors import InputError
from storage.inputs.identity import assign_source_ids, discover, fingerprint

BUCKET = "ms3d-inputs-test"
KEY_ID = "AKIAMS3DINPUTSKEY001"
SECRET = "ms3d-inputs-secret-DO-NOT-LOG-51c2"


@pytest.fixture(scope="module")
def s3_server(moto_s3):
    """The session's moto S3 server on 127.0.0.1 with this module's bucket; yields the endpoint URL."""
    return moto_s3(BUCKET, KEY_ID, SECRET)


@pytest.fixture
def s3(s3_server, monkeypatch, tmp_path):
    """The AWS environment pointing at the local server, an empty input cache; yields a put(key, bytes)
    that returns the object's URL."""
    import boto3

    from storage.inputs import remote as remote_inputs

    for k in ("AWS_PROFILE", "AWS_ENDPOINT_URL_S3", "AWS_SESSION_TOKEN"):
        monkeypatch.delenv(k, raising=False)
    env = {"AWS_ENDPOINT_URL": s3_server, "AWS_ACCESS_KEY_ID": KEY_ID, "AWS_SECRET_ACCESS_KEY": SECRET,
           "AWS_DEFAULT_REGION": "us-east-1", "MS3D_CACHE": str(tmp_path / "cache")}
    for k, v in env.items():
        monkeypatch.setenv(k, v)
    monkeypatch.setattr(remote_inputs, "_STORES", {})
    client = boto3.client("s3", endpoint_url=s3_server, region_name="us-east-1")
    prefix = uuid.uuid4().hex[:10]

    def put(key: str, data: bytes) -> str:
        client.put_object(Bucket=BUCKET, Key=f"{prefix}/{key}", Body=data)
        return f"s3://{BUCKET}/{prefix}/{key}"

    return put


def _store_of(url):
    from storage.inputs.remote import bucket_store

    return bucket_store(url)[0]


def test_fingerprint_is_etag_and_size_without_download(s3):
    from storage.inputs.remote import local_input

    url = s3("mls/a.laz", b"x" * 1000)
    store = _store_of(url)
    store.stats.requests.clear()
    fp = fingerprint(url)
    assert store.stats.requests.get("GetObject", 0) == 0 and store.stats.requests["HeadObject"] == 1
    assert fingerprint(url) == fp
    assert s3("mls/a.laz", b"y" * 1000) and fingerprint(url) != fp  # same size, new content: new ETag
    local = local_input(url)
    assert Path(local).read_bytes() == b"y" * 1000 and str(local).startswith(os.environ["MS3D_CACHE"])


def test_staged_once_per_content_and_refreshed_when_the_object_changes(s3):
    from storage.inputs.remote import local_input

    url = s3("mesh/Data/Tile_+000_+000/Tile_+000_+000.obj", b"v 0 0 0\n")
    s3("mesh/Data/Tile_+000_+000/Tile_+000_+000.mtl", b"newmtl m\n")
    s3("mesh/metadata.xml", b"<ModelMetadata/>")
    store = _store_of(url)
    store.stats.requests.clear()
    local = local_input(url, siblings=True)
    assert store.stats.requests["GetObject"] == 3  # the mesh, its .mtl and the production's metadata.xml
    assert os.path.exists(os.path.join(os.path.dirname(local), "Tile_+000_+000.mtl"))
    assert os.path.exists(os.path.join(os.path.dirname(local), "..", "..", "metadata.xml"))
    store.stats.requests.clear()
    assert local_input(url) == local and store.stats.requests.get("GetObject", 0) == 0  # cached
    s3("mesh/Data/Tile_+000_+000/Tile_+000_+000.obj", b"v 1 1 1\nv 2 2 2\n")
    assert Path(local_input(url)).read_bytes() == b"v 1 1 1\nv 2 2 2\n"


def test_folder_url_is_discovered_like_a_local_folder(s3):
    a = s3("campus/mls/a.laz", b"a")
    b = s3("campus/mls/b.las", b"b")
    s3("campus/mls/readme.txt", b"hi")
    s3("campus/mls/.partial.laz", b"")
    m = s3("campus/mesh/Data/Tile_+000_+000/Tile_+000_+000.obj", b"v 0 0 0")
    s3("campus/mesh/Data/Tile_+000_+000/Tile_+000_+000.mtl", b"")
    s3("campus/mesh/Data/Tile_+000_+000/atlas.jpg", b"")
    mesh_dir, mls_dir = m.split("/Data/")[0], a.rsplit("/", 1)[0]
    found = discover([mesh_dir], [mls_dir + "/"])
    assert found.meshes == (m,) and found.points == (a, b)
    assert sorted(why for _, why in found.skipped) == ["hidden or temporary file",
                                                     "not a points file (extension '.txt')"]
    ids = assign_source_ids([m, a, b])
    assert ids == assign_source_ids([b, a, m])  # identity is the URL, the same in every process


def test_a_missing_url_is_one_line_naming_it_without_credentials(s3):
    from storage.inputs.remote import local_input

    url = s3("x/present.laz", b"1").replace("present", "absent")
    for call in (lambda: fingerprint(url), lambda: local_input(url), lambda: discover([url], [url])):
        with pytest.raises(InputError) as e:
            call()
        msg = str(e.value)
        assert url in msg and "\n" not in msg and SECRET not in msg and KEY_ID not in msg


def test_config_keeps_input_and_work_dir_urls_as_written(tmp_path):
    from tasks.config import CampusConfig

    (tmp_path / "c.yaml").write_text(
        "name: t\nwork_dir: s3://b/work\ninputs:\n  mesh: [s3://b/c/mesh]\n  points: [mls]\n"
        "  labels: s3://b/c/truth/defects.json\n  cameras: s3://b/c/sparse/0\n")
    cfg = CampusConfig.from_yaml(tmp_path / "c.yaml")
    assert cfg.work_dir == "s3://b/work" and cfg.inputs.mesh == ["s3://b/c/mesh"]
    assert cfg.inputs.points == [str(tmp_path / "mls")]  # a relative path still joins the config's folder
    assert (cfg.inputs.labels, cfg.inputs.cameras) == ("s3://b/c/truth/defects.json", "s3://b/c/sparse/0")


def test_registration_samples_a_laz_object_by_range_reads(s3, tmp_path):
    """The registration sample of a LAZ object by URL is read through range GETs (header, chunk table, the
    ranges' chunks), not by staging the file: the same points as from the local file, a part of its bytes,
    and nothing in the input cache."""
    from types import SimpleNamespace

    import numpy as np

    from storage.formats.las import write_points
    from storage.formats.point_chunk import PointChunk
    from tasks.config import CampusConfig
    from tasks.register.stage import sample_points_for_registration

    n = 1_600_000  # 32 LAZ chunks of 50,000 points
    rng = np.random.default_rng(5)
    xyz = np.array([500_000.0, 4_000_000.0, 50.0]) + np.cumsum(rng.normal(0, 0.01, (n, 3)), axis=0)
    path = write_points(tmp_path / "strip.laz", PointChunk(xyz=xyz, gps_time=np.arange(n, dtype=np.float64)))
    url = s3("inputs/strip.laz", path.read_bytes())
    cfg = CampusConfig.model_validate({})
    local = sample_points_for_registration(SimpleNamespace(path=str(path), count=n), 8_000, cfg, n_ranges=4)
    store = _store_of(url)
    before = store.stats.bytes_read
    remote = sample_points_for_registration(SimpleNamespace(path=url, count=n), 8_000, cfg, n_ranges=4)
    read = store.stats.bytes_read - before
    assert len(local) == 8_000 and np.array_equal(remote, local)
    assert read < 0.35 * path.stat().st_size, (read, path.stat().st_size)  # 4 ranges of 32 chunks
    assert not (tmp_path / "cache" / "inputs").exists() or not any((tmp_path / "cache" / "inputs").rglob("*.laz"))
