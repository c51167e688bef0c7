"""One tile's merge on arrays: which faces the tile owns, which store faces no region replaces, and the
weld of both into one :class:`storage.contracts.tile_mesh.TileMesh`. No I/O here (:mod:`tasks.merge.stage` reads).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from storage.contracts.region_mesh import RegionMesh
from storage.contracts.tile_mesh import TileMesh
from storage.errors import EmptyTileError, InputError
from storage.grid import PatchGrid
from storage.ids import TileId
from tasks.merge.soup import FaceSoup, WeldStats, concat_soups, region_soup, store_soup, weld_soup

STORE_FACE_COLUMNS = ([f"{a}{v}" for v in range(3) for a in "xyz"] + [f"vid{v}" for v in range(3)]
                      + [f"{a}{v}" for v in range(3) for a in "uv"]
                      + ["texture", "red", "green", "blue", "patch"])  # fmt: skip


def faces_in_tile(xyz: np.ndarray, grid: PatchGrid, origin, tile: TileId) -> tuple[np.ndarray, np.ndarray]:
    """Which faces belong to ``tile`` by the store's rule (the tile holding the centre of the patch
    holding the face centroid). xyz: (m, 3, 3) float32 campus-local; origin: (3,) float64 world.
    Returns ((m,) bool, (m,) int64 patch key of each face)."""
    if len(xyz) == 0:
        return np.zeros(0, bool), np.zeros(0, np.int64)
    cells = grid.face_cells([xyz[:, v, a] for v in range(3) for a in range(3)], origin)
    t = grid.tile_of_cells(cells)
    return (t[:, 0] == tile.ix) & (t[:, 1] == tile.iy), grid.pack(cells)


@dataclass(frozen=True)
class MergeStats:
    """What one tile's merge did: faces of the store retained / replaced, rebuilt faces taken (and
    how many of them lie in a patch whose original faces were retained: a sign that a region overlaps
    the retained mesh), the weld's counts, regions used."""

    retained_faces: int
    replaced_faces: int
    rebuilt_faces: int
    rebuilt_in_retained_patches: int
    weld: WeldStats
    regions: tuple[int, ...] = field(default_factory=tuple)

    def to_json(self) -> dict:
        return {"retained_faces": self.retained_faces, "replaced_faces": self.replaced_faces,
                "rebuilt_faces": self.rebuilt_faces, "rebuilt_in_retained_patches": self.rebuilt_in_retained_patches,
                "faces": self.weld.faces_out, "vertices": self.weld.vertices,
                "duplicates_dropped": self.weld.duplicates, "degenerate_dropped": self.weld.degenerate,
                "split_vertices": self.weld.split_vertices, "regions": list(self.regions)}  # fmt: skip


def retained_soup(cols: dict[str, np.ndarray], face_grade: np.ndarray, regions: Sequence[RegionMesh]
                  ) -> tuple[FaceSoup, np.ndarray, int]:
    """The store faces of a tile that no region replaces (by patch or by row).

    cols: the tile's store face columns (:data:`STORE_FACE_COLUMNS`), (m,) each; face_grade: (m,) int8
    grade of each row's patch; regions: the rebuilt regions reaching into the tile.
    Returns (their soup, (r,) int64 sorted keys of the patches holding them, number of faces replaced).
    """
    patch = cols["patch"]
    replaced = np.zeros(len(patch), bool)
    if regions:
        replaced = np.isin(patch, np.concatenate([r.replaced_patches for r in regions]))
        for r in regions:
            if r.replaced_rows is not None and len(r.replaced_rows):
                if r.replaced_rows.min() < 0 or r.replaced_rows.max() >= len(patch):
                    raise InputError(None, f"rebuilt region {r.region} replaces rows outside the tile's faces "
                                     "(the region is older than the store: rerun the repair)")
                replaced[r.replaced_rows] = True
    if not replaced.any():
        return store_soup(cols, face_grade), np.unique(patch), 0
    keep = np.flatnonzero(~replaced)
    return store_soup(cols, face_grade[keep], rows=keep), np.unique(patch[keep]), int(replaced.sum())


@dataclass(frozen=True, eq=False)
class RebuiltParts:
    """The faces of the rebuilt regions that a tile owns, ready to concatenate after the retained soup.

    parts: one soup per region owning a face of the tile (region number order); textures: the store's
    texture paths followed by the regions' atlases (what the soups' ``texture`` indexes); rebuilt: faces
    in parts; overlap: those lying in a patch whose original faces were retained; regions: every region
    number given, ascending."""

    parts: list[FaceSoup]
    textures: list[str]
    rebuilt: int
    overlap: int
    regions: tuple[int, ...]


def rebuilt_parts(tile: TileId, regions: Sequence[RegionMesh], textures: Sequence[str], grid: PatchGrid, origin,
                  retained_patches: np.ndarray) -> RebuiltParts:
    """The faces of ``regions`` that ``tile`` owns (:func:`faces_in_tile`), one small soup per region, so
    the caller may drop the regions before welding. Arguments as :func:`merge_tile`."""
    regions = sorted(regions, key=lambda r: r.region)
    if len({r.region for r in regions}) != len(regions):
        raise InputError(None, f"tile {tile.key}: two rebuilt regions with one region number")
    all_textures = list(textures)
    parts, rebuilt, overlap = [], 0, 0
    for rank, r in enumerate(regions):
        index = -1
        if r.atlas is not None:
            if r.atlas not in all_textures:
                all_textures.append(r.atlas)
            index = all_textures.index(r.atlas)
        soup = region_soup(r, index, rank)
        own, face_patch = faces_in_tile(soup.xyz, grid, origin, tile)
        if own.any():
            rows = np.flatnonzero(own)
            parts.append(soup.take(rows))
            rebuilt += len(rows)
            overlap += int(np.isin(face_patch[rows], retained_patches).sum())
    return RebuiltParts(parts, all_textures, rebuilt, overlap, tuple(r.region for r in regions))


def weld_tile(tile: TileId, soup: FaceSoup, rebuilt: RebuiltParts, retained_faces: int, replaced_faces: int
              ) -> tuple[TileMesh, MergeStats]:
    """Weld a tile's soup (the retained soup, then ``rebuilt.parts``, concatenated) into its merged mesh.
    Raises EmptyTileError when no face is left."""
    if soup.n_faces == 0:
        raise EmptyTileError(None, f"tile {tile.key}: no faces left after merging")
    mesh, weld = weld_soup(tile.key, soup, rebuilt.textures)
    if mesh.n_faces == 0:
        raise EmptyTileError(None, f"tile {tile.key}: every face is degenerate")
    return mesh, MergeStats(retained_faces, replaced_faces, rebuilt.rebuilt, rebuilt.overlap, weld, rebuilt.regions)


def merge_tile(tile: TileId, retained: FaceSoup, retained_patches: np.ndarray, textures: Sequence[str],
               regions: Sequence[RegionMesh], grid: PatchGrid, origin, replaced_faces: int = 0
               ) -> tuple[TileMesh, MergeStats]:
    """One tile's merged mesh: the retained faces (:func:`retained_soup`) and the faces of ``regions``
    that the tile owns (:func:`rebuilt_parts`), welded (:func:`weld_tile`).

    textures: the store's texture paths (what ``retained.texture`` indexes); regions: the rebuilt
    regions reaching into the tile (any order); grid, origin: the campus patch grid and (3,) float64
    world origin; replaced_faces: carried into the stats. Raises EmptyTileError when no face is left.
    (The stage runs the same three steps, dropping each input as soon as it is used.)
    """
    rebuilt = rebuilt_parts(tile, regions, textures, grid, origin, retained_patches)
    soup = concat_soups([retained, *rebuilt.parts]) if rebuilt.parts else retained
    return weld_tile(tile, soup, rebuilt, retained.n_faces, replaced_faces)
