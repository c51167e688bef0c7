import json

import numpy as np
import pytest

from storage.errors import InputError
from storage.grid import PatchGrid
from storage.workdir.labels import (
    bad_keys_from_csv,
    bad_keys_from_defects,
    bad_keys_from_faces,
    labels_for_patches,
    load_defect_faces,
    load_defect_samples,
    read_labels_csv,
)
from tasks.partition.kernels import point_cells

SIZE = (2.3, 1.0, 0.7)
GRID = PatchGrid(SIZE, 100.0)


def _keys(ijk):
    return PatchGrid.pack(np.asarray(ijk))


def test_defect_keys_are_the_partition_keys_whatever_the_origin():
    rng = np.random.default_rng(0)
    world = rng.normal(0, 500, (5000, 3)) + [500_000.0, 4_200_000.0, 0.0]
    for origin in ([500_000.0, 4_200_000.0, 0.0], [499_000.0, 4_199_000.0, 0.0]):
        local = (world - origin).astype(np.float32)
        from_store = PatchGrid.pack(point_cells(local, GRID, origin))
        direct = PatchGrid.pack(GRID.cells_world(local.astype(np.float64) + origin))
        assert np.array_equal(from_store, direct)


def test_labels_from_defects(tmp_path):
    frame_origin = [10.0, 0.0, 10.0]
    doc = {
        "frame_origin": frame_origin,
        "defects": [
            {"kind": "hole", "samples": [[-5.0, 2.5, -9.0], [-4.9, 2.6, -9.0]], "faces": [10, 11]},  # local (5, 2.5, 1)
            {"kind": "melt", "samples": [[-10.1, -0.1, -10.1]], "faces": [7]},                      # local (-0.1, ...)
            {"kind": "none", "samples": [], "faces": []},
        ],
    }
    path = tmp_path / "defects.json"
    path.write_text(json.dumps(doc))
    world, ids = load_defect_samples(path)
    assert world.dtype == np.float64 and world.shape == (3, 3)
    assert np.allclose(world[0], [5.0, 2.5, 1.0]) and ids.tolist() == [0, 0, 1]
    bad = bad_keys_from_defects(path, GRID)
    assert np.array_equal(bad, np.sort(_keys([[2, 2, 1], [-1, -1, -1]])))
    present = _keys([[2, 2, 1], [0, 0, 0], [-1, -1, -1], [2, 2, 2]])
    assert labels_for_patches(present, bad).tolist() == [1, 0, 1, 0]
    assert labels_for_patches(present, bad).dtype == np.int8
    faces, fids = load_defect_faces(path)
    assert faces.tolist() == [10, 11, 7] and fids.tolist() == [0, 0, 1]


def test_labels_from_defect_faces():
    src_face = np.array([5, 10, 7, 99])
    face_patch = np.array([40, 41, 41, 42])
    assert bad_keys_from_faces(np.array([10, 7]), src_face, face_patch).tolist() == [41]


def test_defects_errors_name_the_file(tmp_path):
    p = tmp_path / "defects.json"
    p.write_text("{not json")
    with pytest.raises(InputError, match="defects.json"):
        load_defect_samples(p)
    p.write_text(json.dumps({"defects": []}))
    with pytest.raises(InputError, match="frame_origin"):
        load_defect_samples(p)
    p.write_text(json.dumps({"frame_origin": [0, 0, 0], "defects": [{"samples": [[1, 2]]}]}))
    with pytest.raises(InputError, match="defect 0"):
        load_defect_samples(p)
    with pytest.raises(InputError, match="not found"):
        load_defect_samples(tmp_path / "missing.json")


def test_labels_from_csv(tmp_path):
    p = tmp_path / "labels.csv"
    p.write_text("i,j,k,label\n2,2,1,1\n-1,-1,-1,0\n# comment\n\n5,0,3\n")
    keys, labels = read_labels_csv(p)
    assert np.array_equal(keys, _keys([[2, 2, 1], [-1, -1, -1], [5, 0, 3]]))
    assert labels.tolist() == [1, 0, 1] and labels.dtype == np.int8
    assert np.array_equal(bad_keys_from_csv(p), np.sort(_keys([[2, 2, 1], [5, 0, 3]])))
    p.write_text("1,2,3\n")  # no header, no label column
    assert np.array_equal(bad_keys_from_csv(p), _keys([[1, 2, 3]]))


@pytest.mark.parametrize("text, problem", [
    ("i,j,k\n1,2\n", "line 2: expected i,j,k"),
    ("1,2,x\n", "line 1: non-integer"),
    ("1,2,3,7\n", "label must be 0"),
    ("1.5,2,3\n", "non-integer"),
])
def test_csv_errors_name_file_and_line(tmp_path, text, problem):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError, match=problem) as e:
        bad_keys_from_csv(p)
    assert e.value.path == str(p)
