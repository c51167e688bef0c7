"""An input object by URL as a seekable, read-only file that fetches only the blocks it reads.

Registration samples a few short point ranges of every MLS file (:mod:`tasks.register.stage`); a LAZ file's
chunk table locates each range, so the sample needs the header, the chunk table and a few chunks: a few MB
of a multi-GB file. Staging the file whole (:func:`storage.inputs.remote.local_input`) put every input of the
campus on the one node that registers, at city scale the whole MLS (~TB). :class:`RangeFile` reads through
range GETs of ``block_bytes`` (256 KiB: a LAZ chunk of 50,000 points is 0.3-1 MB; aligned, so neighbouring reads share a block), keeps the last ``max_blocks``
in memory (LRU) and counts its requests and bytes on the bucket's store (``Store.stats``).

>>> import tempfile, os
>>> from storage.objstore.store import open_store
>>> d = tempfile.mkdtemp()
>>> with open(os.path.join(d, "o.bin"), "wb") as f:
...     _ = f.write(bytes(range(256)) * 64)
>>> rf = RangeFile(open_store(d), "o.bin", block_bytes=1024)
>>> _ = rf.seek(1000); rf.read(4), rf.tell(), rf.blocks_fetched
(b'\\xe8\\xe9\\xea\\xeb', 1004, 1)
>>> len(rf.read()), rf.blocks_fetched   # to the end: 15 more blocks
(15380, 16)
"""

from __future__ import annotations

import io
from collections import OrderedDict


class RangeFile(io.RawIOBase):
    """Read-only, seekable view of object ``key`` of ``store`` (a :class:`storage.objstore.store.Store`),
    read in aligned blocks of ``block_bytes`` by range GETs; ``size``: the object's size when known (else one
    HEAD). ``blocks_fetched``: range GETs so far."""

    def __init__(self, store, key: str, size: int | None = None, *, block_bytes: int = 1 << 18,
                 max_blocks: int = 16, name: str | None = None):
        super().__init__()
        self.store, self.key = store, key
        self.size = int(store.size(key) if size is None else size)
        self.block_bytes, self.max_blocks = int(block_bytes), int(max_blocks)
        self.name = name or key
        self.blocks_fetched = 0
        self._pos = 0
        self._blocks: OrderedDict[int, bytes] = OrderedDict()

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self._pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        base = {io.SEEK_SET: 0, io.SEEK_CUR: self._pos, io.SEEK_END: self.size}[whence]
        pos = base + int(offset)
        if pos < 0:
            raise ValueError(f"negative seek position {pos}")
        self._pos = pos
        return pos

    def _block(self, b: int) -> bytes:
        data = self._blocks.get(b)
        if data is None:
            a = b * self.block_bytes
            data = self.store.get_range(self.key, a, min(a + self.block_bytes, self.size))
            self.blocks_fetched += 1
            self._blocks[b] = data
            while len(self._blocks) > self.max_blocks:
                self._blocks.popitem(last=False)
        else:
            self._blocks.move_to_end(b)
        return data

    def readinto(self, buf) -> int:
        view = memoryview(buf).cast("B")
        n = max(0, min(len(view), self.size - self._pos))
        done = 0
        while done < n:
            b, off = divmod(self._pos + done, self.block_bytes)
            data = self._block(b)[off:off + n - done]
            if not data:
                break
            view[done:done + len(data)] = data
            done += len(data)
        self._pos += done
        return done


def open_range(url: str, size: int | None = None, **kw) -> RangeFile:
    """A :class:`RangeFile` over the object at ``url`` (its bucket's shared Store)."""
    from storage.inputs.remote import bucket_store

    store, key = bucket_store(url)
    return RangeFile(store, key, size, name=url, **kw)


__all__ = ["RangeFile", "open_range"]
