"""3D Tiles archives (export.archive: 3tz): the index layout, every entry read back through the index with this
project's own reader, the export's archive rewritten only when its files change, and the viewer server
serving an archive as it serves a folder."""

from __future__ import annotations

import hashlib
import json
import shutil
import struct
import urllib.error
import urllib.request
import zipfile

import numpy as np
import pytest

from storage.errors import InputError
from storage.formats.threetz import INDEX_NAME, ThreeTzReader, build_index, path_hash_key, write_3tz
from tasks.config import ExportConfig
from tasks.export import run_export


def _index_rows(data: bytes) -> list[tuple[bytes, int]]:
    return [(data[i : i + 16], struct.unpack_from("<Q", data, i + 16)[0]) for i in range(0, len(data), 24)]


def test_index_sorts_by_two_little_endian_uint64():
    names = [f"content/{i}.glb" for i in range(200)]
    rows = _index_rows(build_index(names, list(range(200))))
    keys = [struct.unpack("<QQ", h) for h, _ in rows]
    assert keys == sorted(keys)
    # not the bytes' lexicographic order: the first 8 bytes compare as a little-endian number
    assert [h for h, _ in rows] != sorted(h for h, _ in rows)
    by_hash = {h: off for h, off in rows}
    assert all(by_hash[hashlib.md5(n.encode()).digest()] == i for i, n in enumerate(names))
    assert path_hash_key("\\content\\0.glb") == path_hash_key("content/0.glb")


def test_archive_round_trip_on_the_implicit_export(tiny_merged, tmp_path):
    work = tmp_path / "work"
    shutil.copytree(tiny_merged, work, ignore=shutil.ignore_patterns("1_*", "2_*"))  # tiles 0_0, 0_1
    summary = run_export(work, ExportConfig(tiling="implicit", archive="3tz"))
    out = work / "output"
    arc = summary["archive"]
    assert arc["written"] and arc["path"] == str(out / "tileset.3tz")
    files = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()
                   and p.name not in ("tileset.3tz", "tileset.fingerprints.json"))
    assert "subtrees/0/0/0.subtree" in files and "overview.glb" in files and "georef.json" in files
    assert arc["entries"] == len(files)

    with zipfile.ZipFile(out / "tileset.3tz") as zf:  # an ordinary ZIP too: index last, stored, no comment
        infos = zf.infolist()
        names = [i.filename for i in infos]
        assert names[0] == "tileset.json" and names[-1] == INDEX_NAME and sorted(names[:-1]) == files
        assert infos[-1].compress_type == zipfile.ZIP_STORED and infos[-1].comment == b""
        assert all(i.flag_bits & 0x08 == 0 for i in infos)  # sizes and CRC in every local header
        kinds = {i.filename: i.compress_type for i in infos}
        assert kinds["tileset.json"] == kinds["subtrees/0/0/0.subtree"] == zipfile.ZIP_DEFLATED
        assert kinds["overview.glb"] == zipfile.ZIP_STORED
        offsets = {i.filename: i.header_offset for i in infos}
        index = zf.read(INDEX_NAME)
    rows = _index_rows(index)
    assert len(rows) == len(files)
    assert {h: off for h, off in rows} == {hashlib.md5(f.encode()).digest(): offsets[f] for f in files}
    assert [struct.unpack("<QQ", h) for h, _ in rows] == sorted(struct.unpack("<QQ", h) for h, _ in rows)

    reader = ThreeTzReader(out / "tileset.3tz")
    for f in files:  # every entry, through the index, byte for byte
        assert reader.read(f) == (out / f).read_bytes(), f
    assert reader.read("content/9/9/9.glb") is None and "tileset.fingerprints.json" not in reader
    size, chunks = reader.open_entry("overview.glb", chunk=4096)
    assert size == (out / "overview.glb").stat().st_size and b"".join(chunks) == (out / "overview.glb").read_bytes()

    mtime = (out / "tileset.3tz").stat().st_mtime_ns
    again = run_export(work, ExportConfig(tiling="implicit", archive="3tz"))
    assert not again["archive"]["written"] and (out / "tileset.3tz").stat().st_mtime_ns == mtime
    explicit = run_export(work, ExportConfig(archive="3tz"))  # the layout changed: so does the archive
    assert explicit["archive"]["written"] and "subtrees/0/0/0.subtree" not in ThreeTzReader(out / "tileset.3tz")
    assert ThreeTzReader(out / "tileset.3tz").read("tileset.json") == (out / "tileset.json").read_bytes()
    run_export(work, ExportConfig())
    assert not (out / "tileset.3tz").exists()


def test_not_an_archive_is_one_line_naming_it(tmp_path):
    (tmp_path / "a.json").write_text("{}")
    plain = tmp_path / "plain.3tz"
    with zipfile.ZipFile(plain, "w") as zf:
        zf.write(tmp_path / "a.json", "tileset.json")
    with pytest.raises(InputError, match=r"plain\.3tz: last entry is 'tileset\.json', not an uncommented"):
        ThreeTzReader(plain)
    (tmp_path / "junk.3tz").write_bytes(b"not a zip at all")
    with pytest.raises(InputError, match=r"junk\.3tz: no ZIP end of central directory"):
        ThreeTzReader(tmp_path / "junk.3tz")
    with pytest.raises(ValueError, match="may not hold"):
        write_3tz(tmp_path / "x.3tz", [("inner.3tz", tmp_path / "a.json")])


def test_a_corrupt_entry_fails_its_crc(tmp_path):
    src = tmp_path / "tileset.json"
    src.write_bytes(json.dumps({"asset": {"version": "1.1"}, "pad": list(range(200))}).encode())
    glb = tmp_path / "a.glb"
    glb.write_bytes(np.arange(4096, dtype=np.uint8).tobytes())
    write_3tz(tmp_path / "t.3tz", [("tileset.json", src), ("content/a.glb", glb)])
    data = bytearray((tmp_path / "t.3tz").read_bytes())
    at = data.find(np.arange(4096, dtype=np.uint8).tobytes()[:64])
    data[at + 100] ^= 0xFF
    (tmp_path / "t.3tz").write_bytes(bytes(data))
    with pytest.raises(InputError, match="content/a.glb: CRC-32 mismatch"):
        ThreeTzReader(tmp_path / "t.3tz").read("content/a.glb")


def test_the_viewer_server_serves_an_archive_like_a_folder(tiny_export, tmp_path):
    from flows.view import VIEWER_DIR, start_viewer

    if not (VIEWER_DIR / "node_modules" / "three").is_dir():
        pytest.fail("viewer/node_modules missing (npm ci --prefix viewer)")
    out = tiny_export[0] / "output"
    files = [("tileset.json", out / "tileset.json"), ("content/tiles/0_0.glb", out / "content/tiles/0_0.glb")]
    arc = tmp_path / "t.3tz"
    write_3tz(arc, files)
    server = start_viewer(arc)
    try:
        base = server.url.split("/viewer/")[0]
        for name, path in files:
            with urllib.request.urlopen(f"{base}/output/{name}") as r:
                assert r.read() == path.read_bytes() and int(r.headers["Content-Length"]) == path.stat().st_size
        head = urllib.request.Request(f"{base}/output/content/tiles/0_0.glb", method="HEAD")
        with urllib.request.urlopen(head) as r:
            assert r.headers["Content-Type"] == "model/gltf-binary" and r.read() == b""
        for bad in ("/output/points/tileset.json", "/output/../campus.json", "/output/" + INDEX_NAME + "x"):
            with pytest.raises(urllib.error.HTTPError):
                urllib.request.urlopen(base + bad)
        assert b"importmap" in urllib.request.urlopen(f"{base}/").read()
    finally:
        server.stop()
    work = tmp_path / "work"  # a work dir whose output is only the archive
    (work / "output").mkdir(parents=True)
    shutil.copyfile(arc, work / "output" / "tileset.3tz")
    server = start_viewer(work)
    try:
        base = server.url.split("/viewer/")[0]
        assert urllib.request.urlopen(f"{base}/output/tileset.json").read() == (out / "tileset.json").read_bytes()
    finally:
        server.stop()


def test_an_archive_of_more_than_65535_entries_is_read_through_its_zip64_end_record(tmp_path):
    src = tmp_path / "a.glb"
    src.write_bytes(b"glb!")
    files = [("tileset.json", src)] + [(f"content/{i}.glb", src) for i in range(66_000)]
    write_3tz(tmp_path / "big.3tz", files)
    assert b"PK\x06\x06" in (tmp_path / "big.3tz").read_bytes()[-200:]  # the ZIP64 end of central directory
    reader = ThreeTzReader(tmp_path / "big.3tz")
    assert len(reader.hi) == 66_001 and reader.read("content/65999.glb") == b"glb!" and "content/66000.glb" not in reader
