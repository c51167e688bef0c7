"""tasks.scan's batching and tasks.ingest's blocked tiles: the stage decisions the flow used to make."""

import numpy as np

from storage.frame import CampusFrame
from storage.grid import PatchGrid
from storage.inputs.identity import InputFile
from tasks.ingest import IngestUnit, blocked_tiles
from tasks.scan import scan_batches


def test_a_mesh_weighs_twenty_times_its_size_in_the_scan_batches(tmp_path):
    files = []
    for name, kind, size in [("m.obj", "mesh", 100)] + [(f"c{i}.las", "points", 500) for i in range(5)]:
        (tmp_path / name).write_bytes(b"x" * size)
        files.append({"path": str(tmp_path / name), "kind": kind, "source": len(files)})
    batches = scan_batches(files, n_workers=1)
    assert len(batches) == 4 and sorted(f["source"] for b in batches for f in b) == list(range(6))
    # 101 * 20 outweighs any two clouds (2 * 501): the mesh is alone in its batch
    assert [f["kind"] for b in batches if any(f["kind"] == "mesh" for f in b) for f in b] == ["mesh"]


def test_a_bad_input_blocks_the_tiles_it_covers_and_one_without_bounds_makes_the_campus_incomplete():
    grid = PatchGrid((2.3, 1.0, 0.7), 100.0)
    frame = CampusFrame(origin=(0.0, 0.0, 0.0), crs=None)
    recs = [
        InputFile(1, "/in/good.obj", "mesh", "f1", 10, [0, 0, 0], [50, 50, 10]),
        InputFile(2, "/in/broken.las", "points", "f2", 0, [150, 10, 0], [160, 20, 5], error="broken.las: bad"),
        InputFile(3, "/in/lost.las", "points", "f3", error="lost.las: unreadable"),
        InputFile(4, "/in/late.las", "points", "f4", 100, [10, 210, 0], [20, 220, 5]),
    ]
    units = [IngestUnit("p00000004-f4-00000", 4, "/in/late.las", "points", "f4", 0, 100)]
    ingests = [{"unit": units[0].key, "status": "failed", "error": "late.las: truncated"}]
    blocked, failed, incomplete = blocked_tiles(recs, ingests, units, frame, np.eye(4), grid)
    assert failed == {"input broken.las": "broken.las: bad", "input lost.las": "lost.las: unreadable",
                      "input late.las": "late.las: truncated"}
    assert incomplete == ["/in/lost.las"]
    assert set(blocked) == {"1_0", "0_2"}
    assert blocked["1_0"].startswith("blocked: its input broken.las failed")
