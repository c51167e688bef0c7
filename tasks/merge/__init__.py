"""The merge stage: per tile, the retained mesh and the rebuilt regions become one welded mesh.

Reads a tile's store (``faces.parquet``, ``patches.parquet``), its grades under ``repair.grades``
(``grades.parquet`` / ``labels.parquet``, or every patch bad: :func:`storage.patches.state.patch_grades`, the
regions stage's rule), ``campus.json`` (frame) and the rebuilt regions reaching into it (``regions/``:
:mod:`storage.contracts.region_mesh`). Writes ``tiles/{ix}_{iy}/merged.npz`` + ``merged.json``
(:mod:`storage.contracts.tile_mesh`). Invalidated by a change of the store, of the grade table it reads (or of
``repair.grades`` to one that reads another), of the frame, of a rebuilt region touching the tile, or of
the grid.
"""

from storage.contracts.region_mesh import RegionMesh
from tasks.merge.soup import FaceSoup, weld_soup
from tasks.merge.stage import run_merge_tile
from tasks.merge.tile import MergeStats, faces_in_tile, merge_tile, retained_soup

__all__ = ["FaceSoup", "MergeStats", "RegionMesh", "faces_in_tile", "merge_tile", "retained_soup",
           "run_merge_tile", "weld_soup"]
