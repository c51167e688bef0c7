"""3D Tiles 1.1 implicit-tiling subtrees in the binary format (``.subtree``), as bytes and back. Pure.

A subtree file (3D Tiles 1.1, Implicit Tiling, "Subtree Binary Format") is a 24-byte little-endian header
(magic ``subt``, version 1, JSON byte length uint64, binary byte length uint64), the JSON chunk padded with
spaces to a multiple of 8 bytes and the binary chunk padded with zeros likewise. Its JSON names, per kind of
availability, either a bit stream (``{"bitstream": bufferView, "availableCount": n}``) or ``{"constant": 0|1}``
when every bit is equal:

- ``tileAvailability``: one bit per node of the subtree's ``levels`` levels, ``(4**levels - 1) / 3`` bits for
  a quadtree; level by level from the subtree's root, and within a level in Morton (Z) order of the node's
  coordinates relative to the subtree (:func:`morton2`);
- ``contentAvailability`` (a list, one per content): the same layout, for the nodes that have content;
- ``childSubtreeAvailability``: ``4**levels`` bits, one per node one level below the deepest, in Morton order.

Bits are packed least significant first (bit i is bit ``i % 8`` of byte ``i // 8``, the Booleans of the 3D
Metadata Specification). Buffer views start at multiples of 8 bytes. Optional tile metadata is one property
table (``tileMetadata``) of FLOAT64 scalars or fixed-length FLOAT64 arrays, one row per available tile in
bit order; the class (its properties and semantics) lives in the tileset's ``schema``.

>>> sub = Subtree(tiles=np.array([1, 1, 0, 0, 1], bool), content=np.array([1, 0, 0, 0, 1], bool),
...               children=np.zeros(16, bool), properties={"geometricError": np.array([2.0, 1.0, 0.0])})
>>> back = decode_subtree(encode_subtree(sub, "tile"), 2, "doctest.subtree")
>>> back.tiles.astype(int).tolist(), bool(back.children.any()), back.properties["geometricError"].tolist()
([1, 1, 0, 0, 1], False, [2.0, 1.0, 0.0])
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field

import numpy as np

from storage.errors import InputError

MAGIC = b"subt"
VERSION = 1
HEADER = struct.Struct("<4sIQQ")  # magic, version, JSON byte length, binary byte length


def morton2(x, y) -> np.ndarray:
    """Morton (Z-order) index of quadtree coordinates: the bits of ``x`` at the even positions, ``y`` at the
    odd ones; ``x``, ``y``: ints or (n,) arrays below 2**32. Returns uint64 of their shape.

    >>> morton2(0b11, 0b00).item(), morton2(0b1010, 0b0011).item(), morton2([0, 1, 0, 1], [0, 0, 1, 1]).tolist()
    (5, 78, [0, 1, 2, 3])
    """

    def spread(v: np.ndarray) -> np.ndarray:
        v = v & np.uint64(0xFFFFFFFF)
        for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF), (4, 0x0F0F0F0F0F0F0F0F),
                            (2, 0x3333333333333333), (1, 0x5555555555555555)):
            v = (v | (v << np.uint64(shift))) & np.uint64(mask)
        return v

    return spread(np.asarray(x, np.uint64)) | (spread(np.asarray(y, np.uint64)) << np.uint64(1))


def level_offset(level: int) -> int:
    """Index of the first bit of ``level`` (relative to the subtree's root) in a quadtree tile bit stream."""
    return (4**level - 1) // 3


def tile_bits(levels: int) -> int:
    """Bits of a quadtree subtree's tile (and content) availability: every node of ``levels`` levels."""
    return level_offset(levels)


@dataclass(frozen=True)
class Subtree:
    """One quadtree subtree: ``tiles``, ``content`` (n,) bool with n = :func:`tile_bits` (levels), ``children``
    (4**levels,) bool; ``properties``: tile metadata, name -> (k,) or (k, m) float64, one row per available tile
    in bit order (k = tiles.sum())."""

    tiles: np.ndarray
    content: np.ndarray
    children: np.ndarray
    properties: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def levels(self) -> int:
        return (len(self.children).bit_length() - 1) // 2


def _pad(data: bytes, fill: bytes) -> bytes:
    return data + fill * (-len(data) % 8)


def encode_subtree(sub: Subtree, tile_class: str | None = None) -> bytes:
    """The ``.subtree`` bytes of ``sub``; its ``properties`` become the property table of class ``tile_class``
    (required when there are properties)."""
    if len(sub.tiles) != tile_bits(sub.levels) or len(sub.content) != len(sub.tiles):
        raise ValueError(f"{len(sub.tiles)} tile bits for a subtree of {sub.levels} levels")
    binary = bytearray()
    views: list[dict] = []

    def view(data: bytes) -> int:
        binary.extend(b"\0" * (-len(binary) % 8))
        views.append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)})
        binary.extend(data)
        return len(views) - 1

    def availability(bits: np.ndarray) -> dict:
        bits = np.asarray(bits, bool)
        if bits.all() or not bits.any():
            return {"constant": int(bits.all())}
        return {"bitstream": view(np.packbits(bits, bitorder="little").tobytes()), "availableCount": int(bits.sum())}

    doc: dict = {"tileAvailability": availability(sub.tiles), "contentAvailability": [availability(sub.content)],
                 "childSubtreeAvailability": availability(sub.children)}
    if sub.properties:
        if tile_class is None:
            raise ValueError("tile properties need a class")
        count = int(np.count_nonzero(sub.tiles))
        props = {}
        for name, values in sub.properties.items():
            values = np.asarray(values, "<f8")
            if len(values) != count:
                raise ValueError(f"{len(values)} values of {name} for {count} available tiles")
            props[name] = {"values": view(values.tobytes())}
        doc["propertyTables"] = [{"class": tile_class, "count": count, "properties": props}]
        doc["tileMetadata"] = 0
    if views:
        doc = {"buffers": [{"byteLength": len(_pad(bytes(binary), b"\0"))}], "bufferViews": views, **doc}
    text = _pad(json.dumps(doc, separators=(",", ":")).encode(), b" ")
    data = _pad(bytes(binary), b"\0")
    return HEADER.pack(MAGIC, VERSION, len(text), len(data)) + text + data


def decode_subtree(data: bytes, levels: int, name: str = "subtree") -> Subtree:
    """A ``.subtree`` file's availability (and FLOAT64 tile properties) for a quadtree of ``levels`` levels
    per subtree; ``name`` (the file) is named in the InputError a malformed file raises."""
    if len(data) < HEADER.size:
        raise InputError(name, f"{len(data)} bytes: shorter than a subtree header")
    magic, version, n_json, n_bin = HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise InputError(name, f"not a version 1 binary subtree (magic {magic!r}, version {version})")
    if HEADER.size + n_json + n_bin > len(data):
        raise InputError(name, f"truncated: header says {HEADER.size + n_json + n_bin} bytes, file has {len(data)}")
    try:
        doc = json.loads(data[HEADER.size : HEADER.size + n_json])
    except ValueError as e:
        raise InputError(name, f"subtree JSON unreadable: {e}") from None
    binary = data[HEADER.size + n_json : HEADER.size + n_json + n_bin]
    views = doc.get("bufferViews", [])
    if any(b.get("uri") for b in doc.get("buffers", [])):
        raise InputError(name, "external subtree buffers are not read")

    def chunk(index: int) -> bytes:
        if not 0 <= index < len(views) or views[index]["byteOffset"] + views[index]["byteLength"] > len(binary):
            raise InputError(name, f"buffer view {index} missing or outside the binary chunk")
        v = views[index]
        return binary[v["byteOffset"] : v["byteOffset"] + v["byteLength"]]

    def bits(spec: dict | None, n: int, what: str) -> np.ndarray:
        if spec is None:
            raise InputError(name, f"{what} missing")
        if "constant" in spec:
            return np.full(n, bool(spec["constant"]))
        raw = np.frombuffer(chunk(spec["bitstream"]), np.uint8)
        if len(raw) * 8 < n:
            raise InputError(name, f"{what}: {len(raw) * 8} bits for {n} nodes")
        return np.unpackbits(raw, bitorder="little")[:n].astype(bool)

    n = tile_bits(levels)
    contents = doc.get("contentAvailability") or [{"constant": 0}]
    sub_tiles = bits(doc.get("tileAvailability"), n, "tileAvailability")
    props: dict[str, np.ndarray] = {}
    if "tileMetadata" in doc:
        table = doc.get("propertyTables", [])[doc["tileMetadata"]]
        count = int(table["count"])
        for prop, spec in table["properties"].items():
            raw = chunk(spec["values"])
            if count < 1 or len(raw) % (8 * count):
                raise InputError(name, f"tile property {prop}: {len(raw)} bytes for {count} FLOAT64 rows")
            values = np.frombuffer(raw, "<f8").reshape(count, -1)
            props[prop] = values[:, 0] if values.shape[1] == 1 else values
    return Subtree(sub_tiles, bits(contents[0], n, "contentAvailability"),
                   bits(doc.get("childSubtreeAvailability"), 4**levels, "childSubtreeAvailability"), props)
