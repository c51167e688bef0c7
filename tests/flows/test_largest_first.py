"""Classify's units start largest first, so that a long unit does not run alone at the end of the stage."""

from flows.campus import store_sizes
from storage.patches.schema import FACES_FILE, POINTS_FILE
from storage.workdir.layout import WorkDir
from tasks.classify import STAGE
from tasks.stages import BatchContext


def test_tiles_go_largest_store_first_ties_and_missing_stores_in_key_order(tmp_path):
    wd = WorkDir(tmp_path)
    for key, (points, faces) in {"1_1": (10, 5), "1_2": (400, 1), "1_3": (0, 0), "1_4": (100, 300)}.items():
        d = tmp_path / "tiles" / key
        d.mkdir(parents=True)
        (d / POINTS_FILE).write_bytes(b"x" * points)
        (d / FACES_FILE).write_bytes(b"x" * faces)
    (tmp_path / "tiles" / "1_5").mkdir()  # no store yet: counts as empty
    tiles = ["1_1", "1_2", "1_3", "1_4", "1_5", "1_6"]
    sizes = store_sizes(wd, tiles)
    assert sizes == {"1_1": 15, "1_2": 401, "1_3": 0, "1_4": 400, "1_5": 0, "1_6": 0}
    assert STAGE.batch(tiles, BatchContext(2, tiles_per_task=2, weights=sizes)) == [["1_2", "1_4"], ["1_1", "1_3"],
                                                                                   ["1_5", "1_6"]]
