"""A tile's pairs read with the points left in the store (``stream_points``, what the classify stage does so
that its memory does not grow with the MLS density) give the in-memory reader's cues, points and pairs, while
no read holds more than its window of the points table."""

from __future__ import annotations

import numpy as np

from tasks.classify import pairs as pairs_mod
from tasks.classify.evidence import MAX_POINTS_PER_PATCH, strided_ranges
from tasks.classify.pairs import read_tile_pairs


def test_streamed_points_give_the_in_memory_cues_in_bounded_reads(tiny_work, monkeypatch):
    _, wd = tiny_work
    tile = max((wd.tile_dir(t) for t in wd.live_tiles()), key=lambda d: sum(f.stat().st_size for f in d.glob("*.parquet")))
    whole = read_tile_pairs(tile)
    n_points = len(whole.all_points)
    biggest_pair = int((whole._pr[:, 1] - whole._pr[:, 0]).max())
    window = max(n_points // 7, biggest_pair)  # forces several chunks and spans on the tiny tile
    monkeypatch.setattr(pairs_mod, "CUE_POINTS", window)
    monkeypatch.setattr(pairs_mod, "SPAN_ROWS", window)
    reads = []
    real_rows = pairs_mod.StorePoints.rows
    monkeypatch.setattr(pairs_mod.StorePoints, "rows", lambda self, lo, hi: reads.append(hi - lo) or real_rows(self, lo, hi))

    streamed = read_tile_pairs(tile, stream_points=True)
    assert len(streamed) == len(whole) > 50
    np.testing.assert_array_equal(streamed.cues(0), whole.cues(0))
    patches = pairs_mod.PatchStore(tile).patches()
    idx, _ = strided_ranges(patches["point_start"], patches["point_stop"], MAX_POINTS_PER_PATCH)
    np.testing.assert_array_equal(streamed.points_at(idx), whole.all_points[idx])
    some = np.arange(3, 40)
    for a, b in zip(streamed.raw(some)[0], whole.raw(some)[0]):
        np.testing.assert_array_equal(a, b)
    assert len(reads) > 3 and max(reads[:-1]) <= window  # the last read: raw() of a few pairs
    assert sum(reads[:-1]) < 3 * n_points


def test_cue_chunks_bound_pairs_and_spanned_rows():
    rows = np.array([[0, 5], [5, 10], [30, 31], [31, 100], [100, 101]])
    chunks = pairs_mod.cue_chunks(rows, max_pairs=2, max_points=20)
    assert chunks == [(0, 2), (2, 3), (3, 4), (4, 5)]  # 10 -> 31 spans the gap: a new chunk
    assert [i for s, e in chunks for i in range(s, e)] == list(range(len(rows)))
