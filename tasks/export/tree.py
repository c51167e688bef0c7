"""The export quadtree over the ground tiles and the 3D Tiles 1.1 document that describes it. Pure."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tasks.export.georef import GeoRef

EXPORT_VERSION = 4  # 4: parents textured (atlases baked from the children, tasks/export/bake.py); 3: leaves carry per-face quality (face_quality table, _FEATURE_ID_1); 2: LOD meshes decimated in blocks of at most lod.MAX_BLOCK_FACES faces


@dataclass(frozen=True, order=True)
class QuadNode:
    """Node (h, x, y) of the export quadtree: ``h`` levels above the leaves; it covers ground tiles
    ``ix0 + x * 2**h <= ix < ix0 + (x + 1) * 2**h`` (same for y), (ix0, iy0) the minimum tile."""

    h: int
    x: int
    y: int

    @property
    def key(self) -> str:
        return f"L{self.h}_{self.x}_{self.y}"

    @property
    def parent(self) -> QuadNode:
        return QuadNode(self.h + 1, self.x // 2, self.y // 2)


@dataclass(frozen=True)
class QuadTree:
    """levels[h]: the nodes of level h (sorted); children[node]: its children; leaf_tile[node]: "ix_iy"."""

    levels: list[list[QuadNode]]
    children: dict[QuadNode, list[QuadNode]]
    leaf_tile: dict[QuadNode, str]

    @property
    def root(self) -> QuadNode:
        return self.levels[-1][0]


def plan_quadtree(tile_keys: list[str]) -> QuadTree:
    """The quadtree over ground tiles ``tile_keys`` ("ix_iy"), anchored at the minimum tile.

    >>> t = plan_quadtree(["0_0", "1_0", "2_1"])
    >>> [[n.key for n in level] for level in t.levels]
    [['L0_0_0', 'L0_1_0', 'L0_2_1'], ['L1_0_0', 'L1_1_0'], ['L2_0_0']]
    """
    if not tile_keys:
        raise ValueError("no tiles to export")
    ij = np.array([[int(v) for v in k.split("_")] for k in tile_keys])
    lo = ij.min(axis=0)
    span = int((ij.max(axis=0) - lo).max()) + 1
    height = max(0, math.ceil(math.log2(span)))
    leaves = {QuadNode(0, int(i - lo[0]), int(j - lo[1])): k for (i, j), k in zip(ij, tile_keys)}
    levels = [sorted(leaves)]
    children: dict[QuadNode, list[QuadNode]] = {}
    for _ in range(height):
        parents: dict[QuadNode, list[QuadNode]] = {}
        for n in levels[-1]:
            parents.setdefault(n.parent, []).append(n)
        children.update(parents)
        levels.append(sorted(parents))
    return QuadTree(levels, children, leaves)

def tileset_json(tree: QuadTree, nodes: dict[str, dict], georef: GeoRef) -> dict:
    """The 3D Tiles 1.1 document. nodes[key]: {"uri", "box", "geometricError"} per quadtree node."""

    def tile(n: QuadNode) -> dict:
        rec = nodes[n.key]
        t = {"boundingVolume": {"box": rec["box"]}, "geometricError": rec["geometricError"], "refine": "REPLACE",
             "content": {"uri": rec["uri"]}}
        kids = tree.children.get(n, [])
        if kids:
            t["children"] = [tile(c) for c in kids]
        return t

    root = tile(tree.root)
    root = {"transform": georef.tileset_transform(), **root}
    half = np.asarray(root["boundingVolume"]["box"][3:], float).reshape(3, 3)
    diagonal = float(2 * np.linalg.norm(half.sum(axis=0)))
    return {
        "asset": {"version": "1.1", "generator": f"ms3d export v{EXPORT_VERSION}"},
        "geometricError": max(diagonal, root["geometricError"]),
        "root": root,
    }

