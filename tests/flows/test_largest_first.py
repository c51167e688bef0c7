"""Classify's units start largest first, so that a long unit does not run alone at the end of the stage."""

from flows.campus import largest_first
from storage.patches.schema import FACES_FILE, POINTS_FILE
from storage.workdir.layout import WorkDir


def test_tiles_go_largest_store_first_ties_and_missing_stores_in_key_order(tmp_path):
    wd = WorkDir(tmp_path)
    for key, (points, faces) in {"1_1": (10, 5), "1_2": (400, 1), "1_3": (0, 0), "1_4": (100, 300)}.items():
        d = tmp_path / "tiles" / key
        d.mkdir(parents=True)
        (d / POINTS_FILE).write_bytes(b"x" * points)
        (d / FACES_FILE).write_bytes(b"x" * faces)
    (tmp_path / "tiles" / "1_5").mkdir()  # no store yet: counts as empty
    assert largest_first(wd, ["1_1", "1_2", "1_3", "1_4", "1_5", "1_6"]) == ["1_2", "1_4", "1_1", "1_3", "1_5", "1_6"]
