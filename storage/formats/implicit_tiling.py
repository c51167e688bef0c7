"""3D Tiles 1.1 implicit tiling read back: a QUADTREE implicit tileset expanded into explicit tiles (its
subtrees' availability, content uris from the template, boxes derived by halving the root's, or the tile
metadata's TILE_BOUNDING_BOX / TILE_GEOMETRIC_ERROR where the subtrees carry them). Used by the export's
checks and by the tileset reader (:mod:`storage.formats.tiles3d`); ``tasks.export.implicit`` writes them.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from storage.errors import InputError
from storage.formats.subtree import Subtree, decode_subtree, level_offset, morton2

Coord = tuple[int, int, int]  # (level, x, y), level 0 = the root


def template(uri: str, c: Coord) -> str:
    """``uri`` with ``{level}``, ``{x}``, ``{y}`` of tile ``c`` filled in."""
    return uri.replace("{level}", str(c[0])).replace("{x}", str(c[1])).replace("{y}", str(c[2]))


def local_index(c: Coord, origin: Coord) -> tuple[int, int]:
    """(depth below ``origin``, Morton index relative to it) of tile ``c`` in the subtree rooted at ``origin``;
    its tile availability bit is ``level_offset(depth) + index``.

    >>> local_index((3, 5, 2), (2, 2, 1))
    (1, 1)
    """
    d = c[0] - origin[0]
    return d, int(morton2(c[1] - (origin[1] << d), c[2] - (origin[2] << d)))


def derived_box(root_box, c: Coord) -> list[float]:
    """The box implicit tiling derives for tile ``c`` from the root's (quadtree: x and y halved per level).

    >>> derived_box([0, 0, 5, 4, 0, 0, 0, 4, 0, 0, 0, 1], (1, 1, 0))
    [2.0, -2.0, 5.0, 2.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 1.0]
    """
    b = np.asarray(root_box, np.float64)
    n = 2.0 ** c[0]
    ax, ay = b[3:6] / n, b[6:9] / n
    centre = b[:3] + ax * (2 * c[1] + 1 - n) + ay * (2 * c[2] + 1 - n)
    return [float(v) for v in (*centre, *ax, *ay, *b[9:12])]


def expand_implicit(doc: dict, read: Callable[[str], bytes]) -> dict:
    """An implicit tileset (its root's ``implicitTiling``, QUADTREE) as explicit tiles, for checks: each tile
    gets the box and geometricError of its tile metadata (else the derived ones), its content uri, children,
    and ``"implicit": {"coord", "box"}`` (the derived box). ``read(path)``: a subtree file's bytes by its path
    relative to the tileset. Raises InputError (naming the subtree) on an unreadable subtree or availability
    that breaks the rules (content without its tile, a tile without its parent)."""
    root = doc["root"]
    imp = root["implicitTiling"]
    if imp.get("subdivisionScheme") != "QUADTREE" or "box" not in root["boundingVolume"]:
        raise InputError(None, "only QUADTREE implicit tiling with a root box is expanded")
    s, available, box0 = int(imp["subtreeLevels"]), int(imp["availableLevels"]), root["boundingVolume"]["box"]

    def tile(c: Coord, sub: Subtree, origin: Coord, props: dict[int, dict]) -> dict:
        d, index = local_index(c, origin)
        bit = level_offset(d) + index
        meta = props.get(bit, {})
        out = {"boundingVolume": {"box": meta.get("box", derived_box(box0, c))},
               "geometricError": meta.get("geometricError", root["geometricError"] / 2 ** c[0]),
               "refine": root["refine"], "implicit": {"coord": c, "box": derived_box(box0, c)}}
        if sub.content[bit]:
            out["content"] = {"uri": template(root["content"]["uri"], c)}
        kids = []
        for j in (0, 1):
            for i in (0, 1):
                k = (c[0] + 1, 2 * c[1] + i, 2 * c[2] + j)
                if k[0] >= available:
                    continue
                kd, kindex = local_index(k, origin)
                if kd < s and sub.tiles[level_offset(kd) + kindex]:
                    kids.append(tile(k, sub, origin, props))
                elif kd == s and sub.children[kindex]:
                    kids.append(load(k))
        if kids:
            out["children"] = kids
        return out

    def load(c: Coord) -> dict:
        name = template(imp["subtrees"]["uri"], c)
        sub = decode_subtree(read(name), s, name)
        bits = np.flatnonzero(sub.tiles)
        if (sub.content & ~sub.tiles).any():
            raise InputError(name, "content available where its tile is not")
        props = {int(b): {"box": [float(v) for v in sub.properties["boundingBox"][i]],
                          "geometricError": float(sub.properties["geometricError"][i])}
                 for i, b in enumerate(bits)} if "boundingBox" in sub.properties else {}
        out = tile(c, sub, c, props)
        reached = sum(1 for _ in _walk(out, lambda t: t["implicit"]["coord"][0] < c[0] + s))
        if reached != len(bits):
            raise InputError(name, f"{len(bits) - reached} available tiles have no available parent")
        return out

    top = load((0, 0, 0))
    top["transform"] = root.get("transform")
    if top["transform"] is None:
        del top["transform"]
    return {**{k: v for k, v in doc.items() if k != "root"}, "root": top}


def _walk(t: dict, keep: Callable[[dict], bool]):
    """The tiles of ``t``'s tree for which ``keep`` holds, not descending below a tile that fails it."""
    if keep(t):
        yield t
        for c in t.get("children", []):
            yield from _walk(c, keep)
