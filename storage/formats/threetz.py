"""3D Tiles archives (``.3tz``, Maxar's "3D Tiles Archive Format" v1.3): a tileset folder as one ZIP file with
a hash index, written (:func:`write_3tz`) and read (:class:`ThreeTzReader`).

The format: a ZIP archive (ISO/IEC 21320-1) whose entries are stored or deflated, each local file header
carrying its CRC-32 and sizes (no data descriptors), ZIP64 records where offsets pass 4 GiB, ``tileset.json``
at the root, and as the **last** entry, stored and without a comment, ``@3dtilesIndex1@``: 24 bytes per other
entry, the MD5 of its path (``/``-separated, no leading ``/``) then the uint64 little-endian offset of its
local file header, sorted by the MD5 read as two little-endian uint64 (bytes 0-7, then 8-15). No path inside
may contain ``.3tz``.

The writer streams each file into the archive (never whole in memory) through the standard library's ZIP
writer: JSON and subtrees deflated (they shrink several times), everything else stored (the spec's fastest
read; glb images are JPEG or KTX2 already), every timestamp 1980-01-01, so the same files give the same bytes.
The reader is this module's own and, as the spec advises, never lists the central directory: it finds the
end-of-central-directory record (and its ZIP64 counterpart) at the end of the file, the last central entry,
the index, and then each entry by binary search on the hashes.

>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp())
>>> _ = (d / "tileset.json").write_text('{"asset": {"version": "1.1"}}')
>>> _ = write_3tz(d / "t.3tz", [("tileset.json", d / "tileset.json")])
>>> ThreeTzReader(d / "t.3tz").read("/tileset.json")
b'{"asset": {"version": "1.1"}}'
"""

from __future__ import annotations

import hashlib
import shutil
import struct
import zipfile
import zlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path
from storage.errors import InputError

INDEX_NAME = "@3dtilesIndex1@"
INDEX_ENTRY = np.dtype([("hash", "V16"), ("offset", "<u8")])
DEFLATED_SUFFIXES = (".json", ".subtree")
ZIP_EPOCH = (1980, 1, 1, 0, 0, 0)
EOCD = struct.Struct("<4sHHHHIIH")  # signature, disk, cd disk, entries here, entries, cd size, cd offset, comment
EOCD64_LOCATOR = struct.Struct("<4sIQI")  # signature, disk, offset of the ZIP64 end record, disks
EOCD64 = struct.Struct("<4sQHHIIQQQQ")  # signature, size, versions, disks, entries here, entries, cd size, offset
CENTRAL = struct.Struct("<4sHHHHHHIIIHHHHHII")  # ... CRC, sizes, name / extra / comment lengths, ..., offset
LOCAL = struct.Struct("<4sHHHHHIIIHH")  # signature, version, flags, method, time, date, CRC, sizes, name, extra


def normalize(path: str) -> str:
    """An entry path as the index hashes it: ``\\`` to ``/``, no leading ``/``."""
    return path.replace("\\", "/").lstrip("/")


def path_hash_key(path: str) -> tuple[int, int]:
    """(bytes 0-7, bytes 8-15) of the MD5 of the normalized ``path``, each read as little-endian uint64: the
    index's sort key.

    >>> path_hash_key("tileset.json") == path_hash_key("/tileset.json")
    True
    """
    digest = hashlib.md5(normalize(path).encode()).digest()  # the format's hash, not for security
    return struct.unpack("<QQ", digest)


def build_index(names: list[str], offsets: list[int]) -> bytes:
    """The ``@3dtilesIndex1@`` bytes for entries ``names`` whose local file headers are at ``offsets``."""
    rows = sorted((path_hash_key(n), off) for n, off in zip(names, offsets))
    return b"".join(struct.pack("<QQQ", hi, lo, off) for (hi, lo), off in rows)


def write_3tz(dest: str | Path, files: list[tuple[str, Path]]) -> dict:
    """Write the archive ``dest`` (atomically) from ``files``: (entry path, file on disk) pairs, in that order
    (put ``tileset.json`` first), then the index. Returns {"entries", "bytes"}. Raises ValueError on a path
    the format refuses (containing ``.3tz``, or twice)."""
    names = [normalize(n) for n, _ in files]
    bad = [n for n in names if ".3tz" in n or ".3dtiles.zip" in n or n == INDEX_NAME]
    if bad or len(set(names)) != len(names):
        raise ValueError(f"entry paths a 3tz archive may not hold: {bad or 'duplicates'}")
    offsets = []
    with atomic_path(dest) as tmp:
        with zipfile.ZipFile(tmp, "w", allowZip64=True) as zf:
            for name, (_, src) in zip(names, files):
                info = zipfile.ZipInfo(name, ZIP_EPOCH)
                info.compress_type = zipfile.ZIP_DEFLATED if name.endswith(DEFLATED_SUFFIXES) else zipfile.ZIP_STORED
                info.external_attr = 0o644 << 16
                info.file_size = Path(src).stat().st_size
                with open(src, "rb") as f, zf.open(info, "w") as out:
                    shutil.copyfileobj(f, out, 1 << 20)
                offsets.append(info.header_offset)
            index = zipfile.ZipInfo(INDEX_NAME, ZIP_EPOCH)
            index.compress_type = zipfile.ZIP_STORED
            zf.writestr(index, build_index(names, offsets))
        size = tmp.stat().st_size
    return {"entries": len(names), "bytes": size}


class ThreeTzReader:
    """Entries of a ``.3tz`` archive by path, through its index (module docstring). Each call opens the file
    anew, so one reader serves many threads. Raises InputError naming the archive when it is not a 3tz."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        index = self._index()
        if len(index) % INDEX_ENTRY.itemsize:
            raise InputError(self.path, f"{INDEX_NAME} is {len(index)} bytes: not a multiple of 24")
        rows = np.frombuffer(index, INDEX_ENTRY)
        keys = np.frombuffer(rows["hash"].tobytes(), "<u8").reshape(-1, 2)
        self.hi, self.lo, self.offsets = keys[:, 0].copy(), keys[:, 1].copy(), rows["offset"].astype(np.uint64)
        hi, lo = self.hi, self.lo
        if np.any((hi[1:] < hi[:-1]) | ((hi[1:] == hi[:-1]) & (lo[1:] < lo[:-1]))):
            raise InputError(self.path, f"{INDEX_NAME} is not sorted by hash")

    @staticmethod
    def _tail(f, n: int) -> bytes:
        f.seek(max(0, f.seek(0, 2) - n))
        return f.read()

    def _index(self) -> bytes:
        """The index entry's bytes: found from the end of the file, never by listing the central directory."""
        with open(self.path, "rb") as f:
            tail = self._tail(f, EOCD.size + 0xFFFF)
            at = tail.rfind(b"PK\x05\x06")
            if at < 0:
                raise InputError(self.path, "no ZIP end of central directory: not a 3tz archive")
            _, _, _, _, _, cd_size, cd_offset, _ = EOCD.unpack_from(tail, at)
            loc = at - EOCD64_LOCATOR.size
            if loc >= 0 and tail[loc : loc + 4] == b"PK\x06\x07":  # ZIP64: the real sizes are in its end record
                f.seek(EOCD64_LOCATOR.unpack_from(tail, loc)[2])
                rec = EOCD64.unpack(f.read(EOCD64.size))
                cd_size, cd_offset = rec[8], rec[9]
            f.seek(cd_offset + max(0, cd_size - 512))
            cd_tail = f.read(min(cd_size, 512))
            entry = self._last_central(cd_tail)
            local = self._local(f, entry["offset"], INDEX_NAME)
            if local is None:
                raise InputError(self.path, f"the central directory's {INDEX_NAME} has no local header")
            if entry["method"] != 0:
                raise InputError(self.path, f"{INDEX_NAME} is compressed: the format stores it")
            f.seek(local)
            return f.read(entry["size"])

    def _last_central(self, cd_tail: bytes) -> dict:
        """The last central directory entry in ``cd_tail`` (the directory's last bytes), which must be the index."""
        at = len(cd_tail)
        while (at := cd_tail.rfind(b"PK\x01\x02", 0, at)) >= 0:
            h = CENTRAL.unpack_from(cd_tail, at)
            n_name, n_extra, n_comment = h[10], h[11], h[12]
            if at + CENTRAL.size + n_name + n_extra + n_comment == len(cd_tail):
                name = cd_tail[at + CENTRAL.size : at + CENTRAL.size + n_name].decode("utf-8", "replace")
                if name != INDEX_NAME or n_comment:
                    raise InputError(self.path, f"last entry is {name!r}, not an uncommented {INDEX_NAME}: not a 3tz")
                extra = cd_tail[at + CENTRAL.size + n_name : at + CENTRAL.size + n_name + n_extra]
                size, offset = h[9], h[16]
                z64 = iter(_zip64_fields(extra))
                if size == 0xFFFFFFFF:
                    size = next(z64)
                if h[8] == 0xFFFFFFFF:
                    next(z64)  # the compressed size (the index is stored: equal)
                if offset == 0xFFFFFFFF:
                    offset = next(z64)
                return {"method": h[4], "size": size, "offset": offset}
        raise InputError(self.path, "no central directory entry at its end: not a ZIP archive")

    def _local(self, f, offset: int, name: str) -> int | None:
        """The data offset of the entry whose local file header is at ``offset`` when it is named ``name``."""
        f.seek(offset)
        head = f.read(LOCAL.size)
        if len(head) < LOCAL.size or head[:4] != b"PK\x03\x04":
            raise InputError(self.path, f"no local file header at offset {offset}")
        h = LOCAL.unpack(head)
        if h[2] & 0x08:
            raise InputError(self.path, f"entry at {offset} has a data descriptor: the format forbids them")
        got = f.read(h[9])
        if got.decode("utf-8", "replace") != name:
            return None
        return offset + LOCAL.size + h[9] + h[10]

    def _find(self, f, name: str) -> tuple[int, int, int, int, int] | None:
        """(data offset, method, compressed size, uncompressed size, CRC) of entry ``name``; None when absent."""
        hi, lo = path_hash_key(name)
        a, b = np.searchsorted(self.hi, np.uint64(hi), "left"), np.searchsorted(self.hi, np.uint64(hi), "right")
        a = a + np.searchsorted(self.lo[a:b], np.uint64(lo), "left")
        while a < len(self.hi) and self.hi[a] == hi and self.lo[a] == lo:  # equal hashes lie side by side
            off = int(self.offsets[a])
            data = self._local(f, off, normalize(name))
            if data is not None:
                f.seek(off)
                h = LOCAL.unpack(f.read(LOCAL.size))
                z64 = list(_zip64_fields(f.read(h[9] + h[10])[h[9] :]))  # uncompressed, then compressed size
                size, packed = (z64[0] if h[8] == 0xFFFFFFFF else h[8]), (z64[-1] if h[7] == 0xFFFFFFFF else h[7])
                return data, h[3], packed, size, h[6]
            a += 1
        return None

    def __contains__(self, name: str) -> bool:
        with open(self.path, "rb") as f:
            return self._find(f, name) is not None

    def open_entry(self, name: str, chunk: int = 1 << 20) -> tuple[int, Iterator[bytes]] | None:
        """(entry ``name``'s size in bytes, its bytes in chunks: decompressed, CRC-32 checked at the end); None
        when the archive has no such entry. The file is opened when the chunks are first asked for."""
        with open(self.path, "rb") as f:
            found = self._find(f, name)
        if found is None:
            return None
        data, method, packed, size, crc = found
        if method not in (0, 8):
            raise InputError(self.path, f"{name}: compression method {method} is not read (stored or deflate)")
        return size, self._chunks(name, data, method, packed, crc, chunk)

    def _chunks(self, name: str, data: int, method: int, packed: int, crc: int, chunk: int) -> Iterator[bytes]:
        inflate = zlib.decompressobj(-15) if method == 8 else None
        got = 0
        with open(self.path, "rb") as f:
            f.seek(data)
            left = packed
            while left:
                block = f.read(min(chunk, left))
                if not block:
                    raise InputError(self.path, f"{name}: truncated")
                left -= len(block)
                out = inflate.decompress(block) if inflate else block
                got = zlib.crc32(out, got)
                yield out
        if inflate:
            tail = inflate.flush()
            got = zlib.crc32(tail, got)
            yield tail
        if got != crc:
            raise InputError(self.path, f"{name}: CRC-32 mismatch")

    def read(self, name: str) -> bytes | None:
        """Entry ``name``'s bytes (decompressed); None when the archive has no such entry."""
        found = self.open_entry(name)
        return None if found is None else b"".join(found[1])


def _zip64_fields(extra: bytes) -> Iterator[int]:
    """The uint64 values of the ZIP64 extended-information field (id 1) in a header's ``extra`` bytes."""
    at = 0
    while at + 4 <= len(extra):
        tag, n = struct.unpack_from("<HH", extra, at)
        if tag == 1:
            yield from struct.unpack_from(f"<{n // 8}Q", extra, at + 4)
            return
        at += 4 + n
