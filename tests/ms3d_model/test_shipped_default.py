"""The shipped default checkpoint (``ms3d_model/weights/default.pt``) loads, grades, and beats the majority
class on a small fixed labelled set built in code.

The pairs go through the classify stage's own path: a tile's arrays (:class:`tasks.classify.pairs.TilePairs`,
with tile-level open edges from the tile's vertex ids, as ``read_tile_pairs`` computes them) graded by
:func:`tasks.classify.stage.grade_pairs` with the model :func:`tasks.classify.stage.load_model` loads for
``classify.model`` unset. Each pair is a wall (or ground) patch of the default 2.3 x 1.0 x 0.7 m cell,
meshed MVS-like (0.16 m faces, 1 cm vertex noise, welded) inside a wall that continues into the neighbouring
cells (so only real holes are open edges), and scanned MLS-like (~300 points/m^2, 1 cm noise):

- good: the points lie on the mesh;
- bad: the points lie 0.3 m in front of or behind the mesh, or the mesh has a 1.2 x 0.45 m hole the
  points cover.

Balanced (12 good, 12 bad), so the majority class scores 50 %. As on a campus, each scored pair lies in a
wall (or ground) of good cells: its two neighbouring cells along the wall hold good pairs of their own,
which the grader's neighbourhood cues see (:mod:`ms3d_model.context`); they are graded but not scored.
"""

from __future__ import annotations

import numpy as np
import pytest

from ms3d_model.cues import open_edge_flags

CELL_M = np.array([2.3, 1.0, 0.7])
FACE_M = 0.16
DENSITY_PER_M2 = 300.0


def _surface(nu: int, nv: int, hole=None):
    """A (nu x nv) grid of squares in (u, v) in [-1, 2] cell units (the patch is [0, 1]^2 and its 8
    neighbours): vertices (V, 2) in cell units and faces (F, 3) int64; ``hole`` (u0, u1, v0, v1) drops the
    squares whose centre lies inside (cell units)."""
    u, v = np.meshgrid(np.linspace(-1, 2, 3 * nu + 1), np.linspace(-1, 2, 3 * nv + 1), indexing="ij")
    verts = np.stack([u.ravel(), v.ravel()], 1)
    i, j = np.meshgrid(np.arange(3 * nu), np.arange(3 * nv), indexing="ij")
    a = (i * (3 * nv + 1) + j).ravel()
    b, c, d = a + 3 * nv + 1, a + 3 * nv + 2, a + 1
    cu, cv = (i.ravel() + 0.5) / nu - 1, (j.ravel() + 0.5) / nv - 1
    keep = np.ones(len(a), bool)
    if hole is not None:
        keep = ~((cu > hole[0]) & (cu < hole[1]) & (cv > hole[2]) & (cv < hole[3]))
    faces = np.concatenate([np.stack([a, b, c], 1)[keep], np.stack([a, c, d], 1)[keep]])
    return verts, faces


def _pair(kind: str, vertical: bool, seed: int):
    """(points (n, 3), tile faces (F, 3, 3), tile vids (F, 3), in_patch (F,) bool) of one pair, metres in
    the frame of its cell (origin at the cell's corner)."""
    rng = np.random.default_rng(seed)
    # the surface spans the cell along (u: x, v: z) for a wall at y = 0.5, (u: x, v: y) for ground at z = 0.35
    span = np.array([CELL_M[0], CELL_M[2]]) if vertical else CELL_M[:2]
    nu, nv = (np.ceil(span / FACE_M)).astype(int)
    hole = (0.25, 0.77, 0.18, 0.82) if kind == "hole" else None  # ~1.2 m x 0.45 m of a wall
    uv, faces = _surface(nu, nv, hole)

    def place(uv_cells, depth_m):
        u, v = uv_cells[:, 0] * span[0], uv_cells[:, 1] * span[1]
        if vertical:
            return np.stack([u, np.full_like(u, 0.5) + depth_m, v], 1)
        return np.stack([u, v, np.full_like(u, 0.35) + depth_m], 1)

    verts = place(uv, rng.normal(0, 0.01, len(uv)))
    tris = verts[faces]
    centroid_uv = uv[faces].mean(1)
    in_patch = ((centroid_uv >= 0) & (centroid_uv < 1)).all(1)
    n = rng.poisson(DENSITY_PER_M2 * span.prod())
    offset = {"front": -0.3, "behind": 0.3}.get(kind, 0.0)
    pts = place(rng.uniform(0, 1, (n, 2)), offset + rng.normal(0, 0.01, n))
    return pts, tris, faces, in_patch


KINDS = ["good"] * 12 + ["front"] * 4 + ["behind"] * 4 + ["hole"] * 4


def _layout():
    """[(kind, vertical, seed, cell (3,), scored)]: each scored pair b in cell (3b, 0, 0) between two good
    neighbours in cells (3b - 1, 0, 0) and (3b + 1, 0, 0), like a patch of a longer wall."""
    out = []
    for b, kind in enumerate(KINDS):
        vertical = b % 4 != 3  # a quarter of each class lies flat (ground)
        out.append((kind, vertical, 100 + b, (3 * b, 0, 0), True))
        out += [("good", vertical, 1000 + 2 * b + s, (3 * b + d, 0, 0), False) for s, d in ((0, -1), (1, 1))]
    return out


def labelled_tile():
    """The fixed set as one tile's pairs (``TilePairs``; labels (P,) int8, 1 = bad) and which of them are
    scored ((P,) bool: the 24 of :data:`KINDS`, in that order)."""
    from tasks.classify.pairs import TilePairs

    pts_all, pr, tris_all, vids_all, fr, context, cells, labels, scored = [], [], [], [], [], [], [], [], []
    n_pts = n_faces = n_vids = 0
    for b, (kind, vertical, seed, cell, is_scored) in enumerate(_layout()):
        pts, tris, faces, in_patch = _pair(kind, vertical, seed=seed)
        shift = np.array([10.0 * b, 0.0, 0.0])  # pairs far apart in the tile
        yaw = (b % 4) * np.pi / 2 if vertical else 0.0  # walls facing the four ways
        rot = np.array([[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]])
        pts_all.append(pts @ rot.T + shift)
        pr.append((n_pts, n_pts + len(pts)))
        n_pts += len(pts)
        tris = tris @ rot.T + shift
        tris_all.append(tris[in_patch])
        vids_all.append(faces[in_patch] + n_vids)
        fr.append((n_faces, n_faces + int(in_patch.sum())))
        n_faces += int(in_patch.sum())
        context.append((tris[~in_patch], faces[~in_patch] + n_vids))
        n_vids += int(faces.max()) + 1
        cells.append(cell)
        labels.append(kind != "good")
        scored.append(is_scored)
    # the neighbouring cells' faces sit after every pair's (in no pair's range), as another patch's would
    tris = np.concatenate(tris_all + [c[0] for c in context]).astype(np.float32)
    vids = np.concatenate(vids_all + [c[1] for c in context]).astype(np.int64)
    n = len(cells)
    tp = TilePairs("test", np.arange(n, dtype=np.int64) * 101 + 7, np.array(cells, np.int64), np.arange(n),
                   np.array(labels, np.int8), np.ones(n, bool), tuple(CELL_M), np.concatenate(pts_all).astype(np.float32),
                   tris, vids, open_edge_flags(vids), np.array(pr, np.int64), np.array(fr, np.int64))
    return tp, np.array(scored)


@pytest.fixture(scope="module")
def shipped():
    from tasks.classify.stage import DEFAULT_MODEL, load_model

    assert DEFAULT_MODEL.exists(), f"{DEFAULT_MODEL} is not in the checkout"
    return load_model(None)


def test_the_set_is_what_it_claims():
    tp, scored = labelled_tile()
    pts, tris, _, oe = tp.raw(np.flatnonzero(scored))
    assert tp.labels[scored].mean() == 0.5 and scored.sum() == len(KINDS) and tp.labels[~scored].sum() == 0
    from ms3d_model.cues import CUE_NAMES

    nb = tp.cues(0)[:, CUE_NAMES.index("nb_count")]
    assert (nb[scored] == 2).all()  # every scored pair sees its two good neighbours, and only them
    open_m = [float((np.linalg.norm(np.roll(t, -1, 1) - t, axis=2) * o).sum()) for t, o in zip(tris, oe)]
    holes = [k == "hole" for k in KINDS]
    # holes are the only open edges in the tile's sense; their perimeter is about 2 x (1.2 + 0.45) m
    assert all(m == 0 for m, h in zip(open_m, holes) if not h)
    assert all(2.5 < m < 4.5 for m, h in zip(open_m, holes) if h)
    assert all(200 < len(p) < 800 for p in pts) and all(len(t) >= 40 for t in tris)


def test_the_shipped_default_loads_and_grades(shipped):
    from tasks.classify.stage import grade_pairs

    tp, _ = labelled_tile()
    threshold = float(getattr(shipped, "threshold", 0.5))
    scores, grades = grade_pairs(shipped, tp, 16, threshold)
    assert scores.shape == (len(tp),) and scores.dtype == np.float32
    assert np.isfinite(scores).all() and ((scores >= 0) & (scores <= 1)).all()
    np.testing.assert_array_equal(grades, (scores >= threshold).astype(np.int8))
    # grading is deterministic and independent of the batch size
    again, _ = grade_pairs(shipped, tp, 5, threshold)
    np.testing.assert_allclose(again, scores, atol=1e-6)


def test_the_shipped_default_beats_the_majority_class(shipped):
    from tasks.classify.stage import grade_pairs

    tp, scored = labelled_tile()
    threshold = float(getattr(shipped, "threshold", 0.5))
    scores, grades = grade_pairs(shipped, tp, 16, threshold)
    scores, grades, lab = scores[scored], grades[scored], tp.labels[scored]
    acc = float((grades == lab).mean())
    majority = max(lab.mean(), 1 - lab.mean())
    recall_bad = float(grades[lab == 1].mean())
    detail = ", ".join(f"{k}:{s:.2f}" for k, s in zip(KINDS, scores))
    assert acc >= majority + 0.2, f"accuracy {acc:.2f} vs majority {majority:.2f} ({detail})"
    assert recall_bad >= 0.6, f"recall on bad {recall_bad:.2f} ({detail})"
    # and the scores rank bad above good (area under the ROC curve)
    auc = float((scores[lab == 1][:, None] > scores[lab == 0][None, :]).mean())
    assert auc >= 0.8, f"AUC {auc:.2f} ({detail})"


def test_the_training_seeds_the_demo_names_are_the_model_cards():
    """The demo says when its campus is one the shipped default was trained on: that list is the one the model
    card's retrain command for ``default.pt`` gives (``--seeds 7 11 ... 23@0.3 37:coarse``)."""
    from pathlib import Path

    from tasks.classify import DEFAULT_MODEL_TRAINING_SEEDS

    card = (Path(__file__).resolve().parents[2] / "ms3d_model" / "weights" / "MODEL_CARD.md").read_text()
    section = card.split("## `default.pt`", 1)[1]
    retrain = section.split("**Retrain**:", 1)[1].split("--seeds", 1)[1].split("--", 1)[0]
    seeds = tuple(int(t.split("@")[0].split(":")[0]) for t in retrain.split())
    assert 7 in seeds and seeds == DEFAULT_MODEL_TRAINING_SEEDS["demo"], seeds


def test_the_shipped_trees_read_what_the_scan_says_not_the_meshs_structure(shipped):
    """The shipped trees never split on the open-edge cues: on a real production an open edge marks a node
    border, a crack or the end of the capture, not a hole (a real ContextCapture mesh whose scan agrees with
    it everywhere was graded 45 % bad by trees that read them). Nor on the mesh -> point distances: mesh the
    scan did not reach reads the same whether it is a false surface or a part the scanner could not see (on
    the real ContextCapture production they were the first cause of false alarms). The checkpoint's profile
    names them."""
    from ms3d_model.cues import CUE_NAMES

    ignored = set(shipped.profile.gbm_ignored_cues)
    assert {"open_edge_m", "open_edge_count", "nb_max_open_edge_m", "nb_mean_open_edge_m"} <= ignored
    assert {"m2p_mean", "m2p_p90", "m2p_max", "m2p_median", "coverage_10cm", "m2p_frac_25cm",
            "nb_max_m2p_p90", "nb_mean_m2p_p90", "nb_max_coverage_10cm", "nb_mean_coverage_10cm"} <= ignored
    used = {CUE_NAMES[i] for i in np.unique(shipped.net.feature.cpu().numpy()) if 0 <= i < len(CUE_NAMES)}
    assert used and not used & ignored, sorted(used & ignored)
