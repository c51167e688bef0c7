"""Export's bounded working set: the linear vertex split, block-wise decimation, the streamed glb."""

from __future__ import annotations

import numpy as np
import pytest

from storage.atomic import write_parts_atomic
from tasks.export import vertex_split
from tasks.export.gltf import GltfMesh, build_glb, glb_parts, split_by_feature
from tasks.export.lod import LodMesh, decimate, split_blocks


def _sorted_split(faces, feature):
    """The general (sorting) path of split_by_feature, with the linear path switched off."""
    saved = vertex_split._single_feature_split
    vertex_split._single_feature_split = lambda f, x: None
    try:
        return split_by_feature(faces, feature)
    finally:
        vertex_split._single_feature_split = saved


def test_linear_split_equals_the_sorting_split():
    rng = np.random.default_rng(1)
    linear_taken = 0
    for trial in range(100):
        nv, m = int(rng.integers(3, 40)), int(rng.integers(1, 50))
        faces, feature = rng.integers(0, nv, (m, 3)), rng.integers(0, int(rng.integers(1, 5)), m)
        if trial % 2 == 0:  # vertices of different features apart: the linear path applies
            faces = faces + feature[:, None] * nv
        linear_taken += vertex_split._single_feature_split(np.asarray(faces, np.int64), feature) is not None
        fast, slow = split_by_feature(faces, feature), _sorted_split(faces, feature)
        for a, b in zip(fast, slow):
            assert a.dtype == b.dtype and np.array_equal(a, b)
    assert linear_taken >= 50


def _bump_grid(n: int = 61) -> LodMesh:
    """An (n-1) x (n-1) grid of 1 m cells with a 2 m bump: 2 (n-1)^2 faces; every other face in region 3."""
    x, y = np.meshgrid(np.arange(n, dtype=np.float32), np.arange(n, dtype=np.float32))
    z = 2.0 * np.exp(-((x - 30) ** 2 + (y - 30) ** 2) / 60.0)
    pos = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1).astype(np.float32)
    i = (np.arange(n - 1)[:, None] * n + np.arange(n - 1)[None, :]).ravel()
    faces = np.concatenate([np.stack([i, i + 1, i + n], 1), np.stack([i + 1, i + n + 1, i + n], 1)]).astype(np.int32)
    m = len(faces)
    return LodMesh(pos, faces, np.full((len(pos), 3), 100, np.uint8), np.zeros(m, np.int8), np.zeros(m, np.int8),
                   np.where(np.arange(m) % 2 == 0, 3, -1).astype(np.int32))


def _border_edges(faces: np.ndarray) -> int:
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1).astype(np.int64)
    _, count = np.unique(e[:, 0] << 32 | e[:, 1], return_counts=True)
    return int((count == 1).sum())


def test_split_blocks_partitions_the_faces_within_the_bound():
    lod = _bump_grid()
    blocks = split_blocks(lod.positions, lod.faces, 2000)
    assert len(blocks) == 4 and all(len(b) <= 2000 for b in blocks)
    assert np.array_equal(np.sort(np.concatenate(blocks)), np.arange(lod.n_faces))


def test_decimation_in_blocks_welds_its_seams_and_bounds_its_deviation():
    pytest.importorskip("pyfqmr", reason="pyfqmr not installed (pip install pyfqmr)")
    lod = _bump_grid()
    m = lod.n_faces
    whole = decimate(lod, m // 4, samples=5000, backend="fqmr")
    blocks = decimate(lod, m // 4, samples=5000, backend="fqmr", max_block_faces=2000)  # 4 blocks
    assert 0.15 * m < blocks.mesh.n_faces <= 0.3 * m
    assert _border_edges(lod.faces) == _border_edges(blocks.mesh.faces) == 4 * 60  # no crack along a seam
    assert 0.0 < blocks.mean_m < blocks.hausdorff_m < 0.5
    assert blocks.hausdorff_m < 3 * whole.hausdorff_m + 0.01
    assert set(np.unique(blocks.mesh.region).tolist()) == {-1, 3}


def test_glb_parts_stream_the_bytes_build_glb_returns(tmp_path):
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 0, -1], [0, 0, -1], [2, 0, 0]], np.float32)
    mesh = GltfMesh(positions=positions, faces=np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]]),
                    feature=np.array([0, 0, 1]), grade=np.array([0, 1], np.int8), source=np.array([0, 1], np.int8),
                    region=np.array([-1, 7], np.int32), face_texture=np.full(3, -1, np.int16),
                    vertex_colors=np.full((5, 3), 200, np.uint8))
    n = write_parts_atomic(tmp_path / "a.glb", glb_parts(mesh))
    data = (tmp_path / "a.glb").read_bytes()
    assert n == len(data) and data == build_glb(mesh) and len(data) % 4 == 0


def test_two_pass_sort_is_lexsort_on_ties():
    from tasks.export.lod import _lexsort_xyz

    bits = np.random.default_rng(2).integers(0, 3, (500, 3)).astype(np.uint32)  # many ties
    bits[:5, 0] = np.uint32(0xFFFFFFFF)  # the top bit of the 64-bit key
    assert np.array_equal(_lexsort_xyz(bits), np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0])))


def test_leaf_batches_balance_merged_bytes_not_counts(tmp_path):
    from tasks.export import NodeJob, node_batches
    from tasks.export.tree import QuadNode

    jobs = []
    for i, size in enumerate([10] * 8 + [900] + [10] * 9):
        tile = tmp_path / f"{i}_0"
        tile.mkdir()
        (tile / "merged.npz").write_bytes(b"x" * size)
        jobs.append(NodeJob(QuadNode(0, i, 0), "fp", tmp_path, tmp_path, None, None, tile_dir=tile))
    batches = node_batches(jobs, 1)  # at most 8 batches
    assert [i for i, _ in batches[0]] == [8]  # the big tile alone, first; the 17 small ones share 7
    assert sorted(len(b) for b in batches) == [1, 2, 2, 2, 2, 3, 3, 3]


def test_glb_views_of_arrays_empty_or_strided_are_their_bytes():
    from tasks.export.gltf import _Builder

    b = _Builder()
    arrays = [np.zeros((0, 3), np.float32), np.arange(10, dtype=np.uint16).reshape(5, 2)[:, 0], np.ones((3, 4), np.uint8)]
    for a in arrays:
        b.view(a, align=1)
    assert b"".join(b.chunks) == b"".join(np.ascontiguousarray(a).tobytes() for a in arrays)
    assert [v["byteLength"] for v in b.doc["bufferViews"]] == [0, 10, 12]
