"""The regions plan and a rebuilt region on disk: write, then read back what the merge takes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from storage.contracts.region_mesh import (
    clear_region,
    region_meshes_for_tile,
    write_region_doc,
    write_region_mesh,
)
from storage.contracts.region_plan import Region, read_plan, region_dir, write_plan
from storage.grid import PatchGrid
from storage.ids import TileId

GRID = PatchGrid((1.0, 1.0, 1.0), 10.0)


def _region(key: str, cells: list[tuple[int, int, int]]) -> Region:
    keys = np.sort(GRID.pack(np.array(cells)))
    return Region(key, 7, keys, keys[:1], np.zeros(0, np.int64), tiles=("0_0", "1_0"), est_bytes=123)


def _mesh(n_faces_left: int) -> dict:
    """Three faces: ``n_faces_left`` in tile 0_0 (x < 10 m), the rest in 1_0; one replaced row per tile."""
    v = np.array([[9.0, 0.5, 0.5], [9.5, 0.5, 0.5], [9.5, 0.9, 0.5], [10.5, 0.5, 0.5], [10.9, 0.9, 0.5]])
    faces = np.array([[0, 1, 2], [1, 3, 2], [3, 4, 2]])
    cells = [(9, 0, 0)] * n_faces_left + [(10, 0, 0)] * (3 - n_faces_left)
    return {"vertices": v, "vertex_id": np.array([5, 6, -1, -2, 8]), "vertex_source": np.zeros(5, np.int8),
            "faces": faces, "face_patch": GRID.pack(np.array(cells)), "uv": np.full((3, 3, 2), np.nan),
            "face_color": np.full((3, 3), 200), "replaced_tile": np.array([0, 1]), "replaced_row": np.array([4, 2])}


def test_plan_round_trip(tmp_path):
    r = _region("r1", [(9, 0, 0), (10, 0, 0)])
    write_plan(tmp_path, [r], {"0_0": "labels"}, {"0_0": "abc"}, GRID)
    (back,) = read_plan(tmp_path)
    assert back.key == "r1" and back.tiles == r.tiles and back.est_bytes == 123
    assert np.array_equal(back.patches, r.patches) and back.patches.dtype == np.int64
    assert read_plan(tmp_path / "none") == []


def test_a_rebuilt_region_reaches_the_tiles_it_owns_faces_in_or_replaces_rows_of(tmp_path):
    write_plan(tmp_path, [_region("r1", [(9, 0, 0), (10, 0, 0)])], {}, {}, GRID)
    d = region_dir(tmp_path, "r1")
    assert write_region_mesh(d, _mesh(1), np.zeros((2, 3)), np.zeros(2), None) == ["mesh.npz", "fused.npz"]
    assert region_meshes_for_tile(tmp_path, TileId(0, 0)) == []  # no region.json yet: not complete
    write_region_doc(d, {"status": "rebuilt", "replaced_tiles": ["0_0", "1_0"], "atlas": None,
                         "evidence": {"type": "hole"}})
    left, right = (region_meshes_for_tile(tmp_path, TileId(i, 0)) for i in (0, 1))
    assert len(left) == len(right) == 1 and region_meshes_for_tile(tmp_path, TileId(5, 5)) == []
    for rm, row in ((left[0], 4), (right[0], 2)):
        assert rm.region == 7 and rm.region_id == "r1" and rm.defect_type == "hole" and rm.atlas is None
        assert rm.faces.shape == (3, 3) and rm.faces.dtype == np.int64 and rm.vertices.dtype == np.float32
        assert rm.replaced_rows.tolist() == [row] and rm.face_colors.dtype == np.uint8
    assert left[0].fingerprint.startswith("0_0:") and left[0].fingerprint[4:] == right[0].fingerprint[4:]
    doc = json.loads((d / "region.json").read_text())
    write_region_doc(d, {**doc, "status": "kept"})
    assert region_meshes_for_tile(tmp_path, TileId(0, 0)) == []  # left to the mesh: replaces nothing
    clear_region(d)
    assert not any(d.iterdir())


def test_a_region_mesh_without_an_array_is_refused(tmp_path):
    m = _mesh(1)
    del m["face_patch"]
    with pytest.raises(ValueError, match="face_patch"):
        write_region_mesh(tmp_path, m, np.zeros((0, 3)), np.zeros(0), None)
