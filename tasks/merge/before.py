"""The input mesh of a tile as a :class:`TileMesh`: every face of its store, welded as the merge welds the
retained faces, no region rebuilt. The export writes it as the "before" tileset the viewer compares the
merged model with (``export.before``). Memory: one tile's faces."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.contracts.tile_mesh import TileMesh
from storage.ids import TileId
from storage.patches.read import PatchStore
from storage.patches.state import patch_grades
from tasks.merge.tile import STORE_FACE_COLUMNS, RebuiltParts, retained_soup, weld_tile


def input_tile_mesh(tile: TileId, tile_dir: str | Path, grades_mode: str = "auto") -> TileMesh:
    """Every face of the tile's store (its grades as the merge reads them, ``repair.grades``), welded.
    Raises storage.errors.EmptyTileError when the tile holds no mesh face."""
    store = PatchStore(Path(tile_dir))
    _, grade, _ = patch_grades(store, grades_mode)
    counts = store.patches()["n_faces"].astype(np.int64)
    _, cols = store.read_all(point_columns=[], face_columns=STORE_FACE_COLUMNS)
    soup, _, _ = retained_soup(cols, np.repeat(grade, counts), [])
    del cols
    mesh, _ = weld_tile(tile, soup, RebuiltParts([], list(store.meta.textures), 0, 0, ()), soup.n_faces, 0)
    return mesh


__all__ = ["input_tile_mesh"]
