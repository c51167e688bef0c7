"""The classify stage: grade every (mesh patch, point patch) pair of a tile good or bad with MS3DQE-Net
(or the model a config names), writing ``grades.parquet`` beside the tile's store.

- **Grades**: ``score`` = the network's probability of "bad" (float32), ``grade`` = 1 when the score reaches
  the threshold: ``classify.threshold`` when set, else the one the checkpoint ships (chosen on validation by
  training; 0.5 for older checkpoints), else 0.
- **Patches that are not pairs** get ``grade = -1`` (unknown) and ``score = NaN``:
  faces but no points (roofs, courtyards, anything the street scanner cannot see) have no MLS evidence to
  grade against, and the fusion stage could not rebuild them from points anyway; points but no faces
  (a hole the mesh lost entirely, or cars, people and vegetation the mesh never had) cannot be fed to a
  mesh network. Both kinds are kept visible as unknown for the regions stage to decide (for example, to
  join a points-only patch to a neighbouring bad region). A patch with fewer than
  ``partition.min_faces`` faces or ``partition.min_points`` points counts the same way.
- **Geometric evidence** (``classify.evidence``, on by default; :mod:`tasks.classify.evidence`): a
  patch whose MLS points lie off the mesh is graded bad whatever the network says (its score is kept, so
  such a grade can sit below the threshold), and a points-only patch against the mesh is bad rather than
  unknown (score NaN): a city model looks clean to the network, yet lacks the recesses, balconies and
  passages the scan shows.
- **The user's labels win** (``classify.user_labels``, :mod:`tasks.classify.user`): a patch named in
  ``WORKDIR/labels/*.csv`` (``ms3d view WORKDIR --label``) takes the user's grade, over the model and the
  evidence (the score is kept); the record holds a digest of the tile's labels, so a new label re-grades
  only its tile and repair re-runs only the regions whose grades changed.
- **Resumable**: a tile is skipped when its manifest record matches the store's fingerprint (sizes and
  modification times of its three tables) and the parameters, which include the model's sha256: a new model
  or a re-partitioned tile grades again.
- **One model per worker process**: :func:`load_model` caches networks by (path, size, mtime).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ms3d_model.dataset import PairSet
from storage import recorded
from storage.errors import InputError
from storage.ids import TileId
from storage.patches.read import PatchStore
from storage.patches.schema import PATCHES_FILE, side_table_path
from storage.patches.state import store_fingerprint
from storage.patches.write import write_side_table
from storage.workdir.layout import STALE_FILE, WorkDir
from storage.workdir.user_labels import tile_user_labels
from tasks.classify.evidence import (
    MAX_POINTS_PER_PATCH,
    Evidence,
    offset_evidence,
    range_rows,
    strided_ranges,
    weld_by_ids,
)
from tasks.classify.pairs import (
    empty_pair_set,
    gradable_mask,
    iter_tile_batches,
    read_tile_pairs,
    tile_pair_set,
)
from tasks.classify.user import apply_user_labels, labels_digest
from tasks.units import Done, run_unit

log = logging.getLogger("ms3d.classify")

DEFAULT_MODEL = Path(__file__).resolve().parents[2] / "ms3d_model" / "weights" / "default.pt"
# the synth 'demo' seeds the shipped default was trained on (ms3d_model/weights/MODEL_CARD.md): a campus of one
# of them is no held-out test of it
DEFAULT_MODEL_TRAINING_SEEDS = {"demo": (7, 11, 13, 17, 19, 23, 29, 37, 43, 47, 53, 59, 61, 67, 71, 73, 79, 83, 89)}


@dataclass
class LoadedModel:
    net: object
    profile: object
    hash: str
    path: str
    uses_cues: bool
    threshold: float = 0.5  # the checkpoint's operating threshold (ms3d_model.train.checkpoint_threshold)
    label: str = ""  # what graded: kind and file, e.g. "GBM trees (default.pt)" (ms3d_model.report.model_label)


_MODELS: dict[tuple, LoadedModel] = {}


def model_path(path: str | None) -> Path:
    """The checkpoint a config names, or the shipped default."""
    return Path(path).expanduser().resolve() if path else DEFAULT_MODEL


def load_model(path: str | None) -> LoadedModel:
    """The network of a checkpoint, loaded once per process (``torch.load(weights_only=True)``).

    Raises InputError naming the file when it is missing or not an ms3d checkpoint."""
    p = model_path(path)
    try:
        st = p.stat()
    except OSError:
        raise InputError(p, "model checkpoint not found (classify.model in the config)") from None
    key = (str(p), st.st_size, st.st_mtime_ns)
    if key not in _MODELS:
        from ms3d_model.report import model_label
        from ms3d_model.train import checkpoint_threshold, load_checkpoint, model_hash, net_uses_cues

        try:
            net, profile, meta = load_checkpoint(p)
        except Exception as e:  # noqa: BLE001 - any unreadable checkpoint is the user's input problem
            raise InputError(p, f"not a loadable ms3d model checkpoint ({type(e).__name__}: {e})") from None
        _MODELS[key] = LoadedModel(net, profile, model_hash(p), str(p), net_uses_cues(net), checkpoint_threshold(meta),
                                   model_label(profile.net.to_json(), p))
    return _MODELS[key]


def grading_threshold(ccfg) -> float:
    """The threshold a config grades at: ``classify.threshold`` when set, else the checkpoint's (loads it)."""
    return float(ccfg.threshold) if ccfg.threshold is not None else load_model(ccfg.model).threshold


def grade_pairs(model: LoadedModel, tp, batch_size: int, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Scores (P,) float32 and grades (P,) int8 of a tile's pairs (``tasks.classify.pairs.TilePairs``)."""
    import torch

    from ms3d_model.dataset import to_batch

    prof = model.profile
    scores = np.empty(len(tp), np.float32)
    with torch.inference_mode():
        for idx, feats, cues in iter_tile_batches(tp, batch_size, prof.max_points, prof.max_faces, prof.k_centre,
                                                  prof.seed, with_cues=model.uses_cues,
                                                  with_feats=prof.net.arch != "gbm"):
            logits = model.net(to_batch(feats, cues if model.uses_cues else None))
            scores[idx] = torch.softmax(logits, dim=1)[:, 1].numpy()
    return scores, (scores >= threshold).astype(np.int8)


def tile_evidence(tp, patches: dict, ccfg) -> Evidence:
    """The geometric evidence (:func:`tasks.classify.evidence.offset_evidence`) over every patch of a tile
    read as ``tp`` (:class:`tasks.classify.pairs.TilePairs`: the tile's faces, its points in memory or
    streamed from the store). Only the measured sample of the points is read, and the faces are welded by
    vertex id first: the tile's points are never copied whole, nor its face corners in float64."""
    idx, prow = strided_ranges(patches["point_start"], patches["point_stop"], MAX_POINTS_PER_PATCH)
    n_points = np.asarray(patches["point_stop"], np.int64) - np.asarray(patches["point_start"], np.int64)
    frow = range_rows(patches["face_start"], patches["face_stop"], len(tp.all_triangles))
    fin = frow >= 0
    tris, vids = (tp.all_triangles, tp.all_vids) if fin.all() else (tp.all_triangles[fin], tp.all_vids[fin])
    vertices, faces = weld_by_ids(tris, vids)
    ijk = np.stack([patches["i"], patches["j"], patches["k"]], axis=1)
    return offset_evidence(tp.points_at(idx).astype(np.float64), prow, vertices, faces, frow[fin], ijk,
                           patches["n_faces"], n_points=n_points,
                           off_surface_m=ccfg.evidence_off_surface_m, near_m=ccfg.evidence_near_m,
                           quantile=ccfg.evidence_quantile, min_points=ccfg.evidence_min_points,
                           min_off_points=ccfg.evidence_min_off_points,
                           standing_normal_z=ccfg.evidence_standing_normal_z)


def count_outliers(tile_dir: Path, keys: np.ndarray) -> np.ndarray:
    """(U,) bool: the tile's patches the outliers stage flagged by point or face count (not those merely below
    the minimum counts: those are no pair anyway); all False when the stage wrote no flags."""
    from storage.patches.read import read_side_table

    side = read_side_table(tile_dir, "outliers", keys)
    if side is None:
        return np.zeros(len(keys), bool)
    cols, _ = side
    return np.asarray(cols["outlier_points"], bool) | np.asarray(cols["outlier_faces"], bool)


def run_classify_tile(tile: TileId, cfg, wd: WorkDir) -> dict | None:
    """Grade every pair of one tile into ``grades.parquet``.

    cfg: CampusConfig (uses ``cfg.classify`` and ``cfg.partition.min_faces`` / ``min_points``). Returns the
    unit summary (status, n_pairs, n_bad, n_unknown, pairs_per_s, model_hash, skipped), or None when the tile
    has no live store or classification is disabled (then a stale grades table is removed).
    """
    import torch

    ccfg = cfg.classify
    tile_dir = wd.tile_dir(tile)
    if not ccfg.enabled:
        recorded.unlink(side_table_path(tile_dir, "grades"))
        return None
    if not recorded.is_file(tile_dir / PATCHES_FILE) or recorded.is_file(tile_dir / STALE_FILE):
        return None  # (on a bucket: what the records say, nothing downloaded: the driver plans this way)
    try:
        model = load_model(ccfg.model)
    except InputError as e:
        return {"unit": tile.key, "status": "failed", "error": str(e), "skipped": False}
    fp = store_fingerprint(tile_dir, ("outliers",) if ccfg.outliers == "unknown" else ())
    threshold = float(ccfg.threshold) if ccfg.threshold is not None else model.threshold
    params = {"model_hash": model.hash, "threshold": threshold,
              "min_faces": cfg.partition.min_faces, "min_points": cfg.partition.min_points}
    if ccfg.outliers != "grade":
        params["outliers"] = ccfg.outliers
    if ccfg.evidence:
        params["evidence"] = {k: v for k, v in ccfg.model_dump().items() if k.startswith("evidence_")}
    try:
        ukeys, ulabs = tile_user_labels(wd.root, cfg.grid(), (tile.ix, tile.iy)) if ccfg.user_labels else ((), ())
    except InputError as e:
        return {"unit": tile.key, "status": "failed", "error": str(e), "skipped": False}
    if labels_digest(ukeys, ulabs):
        params["user_labels"] = labels_digest(ukeys, ulabs)

    def work() -> Done:
        t0 = time.perf_counter()
        torch.set_num_threads(ccfg.threads)
        # every pair with a face and a point, as in training: the neighbourhood cues see the same neighbours
        tp = read_tile_pairs(tile_dir, stream_points=True)  # bounded memory at any MLS density
        t_read = time.perf_counter() - t0
        store = PatchStore(tile_dir)
        keys = store.patches()["patch"]
        score = np.full(len(keys), np.nan, np.float32)
        grade = np.full(len(keys), -1, np.int8)
        t1 = time.perf_counter()
        if len(tp):
            s, g = grade_pairs(model, tp, ccfg.batch_size, threshold)
            ok = gradable_mask(store.patches(), cfg.partition.min_faces, cfg.partition.min_points)[tp.rows]
            score[tp.rows[ok]], grade[tp.rows[ok]] = s[ok], g[ok]
        t_grade = time.perf_counter() - t1
        ev = tile_evidence(tp, store.patches(), ccfg) if ccfg.evidence else None
        if ev is not None:
            grade[ev.bad] = 1
        outlier = count_outliers(tile_dir, keys) if ccfg.outliers == "unknown" else np.zeros(len(keys), bool)
        grade[outlier] = -1
        user = apply_user_labels(np.asarray(keys, np.int64), grade, np.asarray(ukeys, np.int64),
                                 np.asarray(ulabs, np.int8))
        t_evidence = time.perf_counter() - t1 - t_grade
        write_side_table(tile_dir, "grades", {"patch": keys, "score": score, "grade": grade}, store.meta,
                         model_hash=model.hash, model=Path(model.path).name, profile=model.profile.name,
                         grader=model.label + (" + the evidence rule" if ev is not None else ""),
                         threshold=threshold, user_labels=int((user >= 0).sum()),
                         outliers=ccfg.outliers, outliers_unknown=int((outlier & (user < 0)).sum()))
        summary = {"tile": tile.key, "n_patches": len(keys), "n_pairs": int(np.isfinite(score).sum()), "n_bad": int((grade == 1).sum()),
                   "n_unknown": int((grade == -1).sum()), "model_hash": model.hash,
                   "n_evidence_bad": int(ev.bad.sum()) if ev is not None else 0,
                   "n_missing_surface": int(ev.missing.sum()) if ev is not None else 0,
                   "n_user_labels": int((user >= 0).sum()),
                   "n_outlier_unknown": int((outlier & (user < 0)).sum()),
                   "read_seconds": t_read, "grade_seconds": t_grade, "evidence_seconds": t_evidence,
                   "pairs_per_s": len(tp) / t_grade if t_grade > 0 and len(tp) else 0.0}
        return Done(outputs=[str(side_table_path(tile_dir, "grades").relative_to(wd.root))], summary=summary)

    return run_unit(wd, "classify", tile.key, fp, params, work)


def campus_pair_set(work_dir: str | Path, campus_name: str, max_points: int, max_faces: int, k_centre: int,
                    seed: int, cache_dir: str | Path | None = None, min_faces: int = 1, min_points: int = 1,
                    labelled_only: bool = True, max_pairs: int | None = None) -> PairSet:
    """Every labelled gradable pair of a processed campus (its live tiles), featurised (cached per tile:
    :func:`tasks.classify.pairs.tile_pair_set`); ``max_pairs``: at most about this many, drawn from the
    tiles in proportion to their pairs."""
    wd = WorkDir(work_dir)
    tiles = wd.live_tiles()
    quota = [None] * len(tiles)
    if max_pairs:
        n = [int(gradable_mask(PatchStore(wd.tile_dir(t)).patches(), min_faces, min_points).sum()) for t in tiles]
        quota = [int(np.ceil(max_pairs * k / max(sum(n), 1))) for k in n]
    parts = [tile_pair_set(wd.tile_dir(t), campus_name, max_points, max_faces, k_centre, seed, cache_dir,
                           min_faces, min_points, labelled_only=labelled_only, max_pairs=q)
             for t, q in zip(tiles, quota)]
    parts = [p for p in parts if len(p)]
    if not parts:
        return empty_pair_set(max_points, max_faces, k_centre, campus_name)
    return PairSet.concat(parts)
