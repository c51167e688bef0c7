"""The export quadtree as 3D Tiles 1.1 implicit tiling (``export.tiling: implicit``): node coordinates, content
and subtree paths, the subtrees, the tileset document, and back (an implicit tileset expanded into explicit
tiles, for the checks: :mod:`storage.formats.implicit_tiling`, re-exported here). Pure: the stage moves the
glbs and writes the files.

Coordinates. :mod:`tasks.export.tree` counts levels up from the leaves (h = 0) and anchors the quadtree at the
minimum ground tile; implicit tiling counts down from the root (level 0). Node (h, x, y) of a tree of height H
is implicit tile (H - h, x, y): a level's x, y already number its squares of 2**h ground tiles from the
anchor, east (x) and north (y), the root box's x and y axes. Content goes to ``content/{level}/{x}/{y}.glb``
(the same glbs, per-face metadata included, only moved), availability to ``subtrees/{level}/{x}/{y}.subtree``.

Bounding volumes. Implicit tiling derives each tile's box by halving the root's along x and y. The root box
is the quadtree's square (2**H ground tiles a side, from the anchor's corner) taken to the ENU frame, as high
as all content, so a tile's derived box is its ground tiles' square. A face belongs to the tile of its patch's
centre, so content overhangs its derived box by up to about a patch; the measured box of every tile (the
explicit tileset's) is written as tile metadata with the TILE_BOUNDING_BOX semantic, which clients that read
tile metadata (CesiumJS) use instead, and which ``check_tileset`` checks. 3d-tiles-renderer (the viewer)
reads no tile metadata: it culls with the derived boxes.

Geometric error. Implicit tiling gives level L the root's error / 2**L. The root's is the smallest value for
which that is at least the measured error of every node: max over levels of (the level's largest error) x
2**L (:func:`root_geometric_error`), so no tile is refined later than in the explicit tileset; a level whose
measured error is less than half its parent level's is refined earlier than needed (more bytes, never less
detail). The measured errors go into the tile metadata too (TILE_GEOMETRIC_ERROR).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from storage.formats.implicit_tiling import Coord, derived_box, expand_implicit, local_index, template  # noqa: F401 (re-exported)
from storage.formats.subtree import Subtree, encode_subtree, level_offset, tile_bits
from tasks.export.georef import GeoRef
from tasks.export.tree import EXPORT_VERSION, QuadNode, QuadTree

CONTENT_URI = "content/{level}/{x}/{y}.glb"
SUBTREE_URI = "subtrees/{level}/{x}/{y}.subtree"
TILE_CLASS = "tile"
SCHEMA = {"id": "ms3d_implicit", "classes": {TILE_CLASS: {"properties": {
    "boundingBox": {"type": "SCALAR", "componentType": "FLOAT64", "array": True, "count": 12,
                    "semantic": "TILE_BOUNDING_BOX"},
    "geometricError": {"type": "SCALAR", "componentType": "FLOAT64", "semantic": "TILE_GEOMETRIC_ERROR"},
}}}}  # fmt: skip


def implicit_coords(tree: QuadTree) -> dict[QuadNode, Coord]:
    """Every node's implicit (level, x, y).

    >>> from tasks.export.tree import plan_quadtree
    >>> sorted(implicit_coords(plan_quadtree(["0_0", "2_1"])).values())
    [(0, 0, 0), (1, 0, 0), (1, 1, 0), (2, 0, 0), (2, 2, 1)]
    """
    height = len(tree.levels) - 1
    return {n: (height - n.h, n.x, n.y) for level in tree.levels for n in level}


def implicit_uris(tree: QuadTree) -> dict[str, str]:
    """Node key -> its content's path in the implicit layout (:data:`CONTENT_URI`)."""
    return {n.key: template(CONTENT_URI, c) for n, c in implicit_coords(tree).items()}


def root_geometric_error(tree: QuadTree, nodes: dict[str, dict]) -> float:
    """The root's geometricError (metres) whose halving per level covers every node's measured error
    (module docstring). nodes[key]["geometricError"]: the measured error.

    >>> from tasks.export.tree import plan_quadtree
    >>> t = plan_quadtree(["0_0", "1_0", "2_0"])
    >>> errors = {"L2_0_0": 0.5, "L1_0_0": 0.3, "L1_1_0": 0.1, "L0_0_0": 0.0, "L0_1_0": 0.0, "L0_2_0": 0.0}
    >>> root_geometric_error(t, {k: {"geometricError": e} for k, e in errors.items()})  # max(0.5, 0.3 * 2)
    0.6
    """
    return float(max(max(nodes[n.key]["geometricError"] for n in tree.levels[h]) * 2.0 ** (len(tree.levels) - 1 - h)
                     for h in range(len(tree.levels))))


def square_box(enu_of: Callable[[np.ndarray], np.ndarray], corner_xy, side_m: float, z_lo: float,
               z_hi: float, pad_m: float = 0.001) -> list[float]:
    """The 3D Tiles ``box`` of the square [corner, corner + side_m]^2 (campus-local metres, x east, y north)
    in the ENU frame: centre and x half-axis from ``enu_of`` ((n, 3) campus-local -> (n, 3) ENU metres) at the
    square's centre and the middles of its west and east sides, levelled; the y half-axis the x one turned
    90 degrees, as long as the square's south-north middle line; z from ``z_lo`` to ``z_hi`` (ENU metres)
    grown by ``pad_m``. A conformal projection keeps the square's corners within millimetres of the box's
    over a few kilometres.

    >>> square_box(lambda p: p - [10.0, 0.0, 0.0], (0.0, 0.0), 8.0, 1.0, 3.0, 0.0)
    [-6.0, 4.0, 2.0, 4.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 1.0]
    """
    uv = np.array([[0.5, 0.5], [0.0, 0.5], [1.0, 0.5], [0.5, 0.0], [0.5, 1.0]])
    local = np.column_stack([np.asarray(corner_xy, np.float64) + uv * side_m, np.zeros(len(uv))])
    e = np.asarray(enu_of(local), np.float64)
    ax = (e[2] - e[1]) / 2
    ax[2] = 0.0
    ay_len = float(np.linalg.norm((e[4] - e[3])[:2]) / 2)
    ay = np.array([-ax[1], ax[0], 0.0]) / np.linalg.norm(ax) * ay_len + 0.0  # + 0.0: no -0.0
    centre = [float(e[0, 0]), float(e[0, 1]), (z_lo + z_hi) / 2]
    return [*centre, *map(float, ax), *map(float, ay), 0.0, 0.0, (z_hi - z_lo) / 2 + pad_m]


def subtree_root(c: Coord, subtree_levels: int) -> Coord:
    """The root of the subtree holding tile ``c``."""
    level0 = c[0] - c[0] % subtree_levels
    d = c[0] - level0
    return level0, c[1] >> d, c[2] >> d


def build_subtrees(tree: QuadTree, nodes: dict[str, dict], subtree_levels: int) -> dict[Coord, Subtree]:
    """Subtree root -> its :class:`Subtree`: every node available with content, each node's measured box
    (nodes[key]["box"], 12 floats) and geometricError as tile metadata. One pass over the nodes."""
    s = subtree_levels
    members: dict[Coord, list[tuple[int, str]]] = {}
    children: dict[Coord, list[int]] = {}
    for n, c in implicit_coords(tree).items():
        root = subtree_root(c, s)
        d, index = local_index(c, root)
        members.setdefault(root, []).append((level_offset(d) + index, n.key))
        if c[0] and d == 0:  # the root of a child subtree: a bit of its parent subtree's row below its last
            parent = subtree_root((c[0] - 1, c[1] >> 1, c[2] >> 1), s)
            children.setdefault(parent, []).append(local_index(c, parent)[1])
    out = {}
    for root, rows in members.items():
        rows.sort()
        tiles = np.zeros(tile_bits(s), bool)
        tiles[[b for b, _ in rows]] = True
        kids = np.zeros(4**s, bool)
        kids[children.get(root, [])] = True
        props = {"boundingBox": np.array([nodes[k]["box"] for _, k in rows], np.float64),
                 "geometricError": np.array([nodes[k]["geometricError"] for _, k in rows], np.float64)}
        out[root] = Subtree(tiles, tiles.copy(), kids, props)
    return out


def implicit_tileset_json(tree: QuadTree, nodes: dict[str, dict], georef: GeoRef, root_box: list[float],
                          subtree_levels: int) -> dict:
    """The 3D Tiles 1.1 document with one implicit root (QUADTREE, ``root_box`` from :func:`square_box`, the
    :func:`root_geometric_error`) and the tile-metadata :data:`SCHEMA`; ``subtree_levels`` is capped at the
    tree's levels."""
    levels = len(tree.levels)
    error = root_geometric_error(tree, nodes)
    half = np.asarray(root_box[3:], float).reshape(3, 3)
    root = {"transform": georef.tileset_transform(), "boundingVolume": {"box": root_box}, "geometricError": error,
            "refine": "REPLACE", "content": {"uri": CONTENT_URI},
            "implicitTiling": {"subdivisionScheme": "QUADTREE", "subtreeLevels": min(subtree_levels, levels),
                               "availableLevels": levels, "subtrees": {"uri": SUBTREE_URI}}}  # fmt: skip
    return {"asset": {"version": "1.1", "generator": f"ms3d export v{EXPORT_VERSION}"}, "schema": SCHEMA,
            "geometricError": max(float(2 * np.linalg.norm(half.sum(axis=0))), error), "root": root}


def implicit_files(tree: QuadTree, nodes: dict[str, dict], georef: GeoRef, corner_xy, tile_size_m: float,
                   enu_of: Callable[[np.ndarray], np.ndarray], subtree_levels: int) -> tuple[dict, dict[str, bytes]]:
    """(the tileset document, subtree path -> ``.subtree`` bytes) of the quadtree as implicit tiling.
    corner_xy: the south-west corner of ground tile 0_0 (campus-local metres), tile_size_m its side, enu_of:
    campus-local -> ENU (:func:`square_box`); nodes[key]: "box", "geometricError", "lo", "hi" (ENU metres)."""
    anchor = np.min([[int(v) for v in k.split("_")] for k in tree.leaf_tile.values()], axis=0)
    z = [r["lo"][2] for r in nodes.values()] + [r["hi"][2] for r in nodes.values()]
    box = square_box(enu_of, np.asarray(corner_xy, np.float64) + anchor * tile_size_m,
                     tile_size_m * 2 ** (len(tree.levels) - 1), min(z), max(z))
    doc = implicit_tileset_json(tree, nodes, georef, box, subtree_levels)
    levels = doc["root"]["implicitTiling"]["subtreeLevels"]
    return doc, {template(SUBTREE_URI, c): encode_subtree(sub, TILE_CLASS)
                 for c, sub in build_subtrees(tree, nodes, levels).items()}
