"""What ``ms3d evaluate`` scores beside the model alone: the shipped grading path, facades, several campuses.

- **The shipped path**: the grades the classify stage wrote (``tiles/*/grades.parquet``: the model at its
  threshold, then the geometric evidence rule, then the user's labels, :mod:`tasks.classify`), matched to the
  labelled pairs by patch. A pair graded "unknown" is not flagged (repair does not rebuild it). Hard grades
  give precision / recall / F1 on bad; AP needs a score, so the shipped row's AP is its stored score with
  every evidence or user override lifted to 1 (bad) or dropped to 0 (good).
- **Facades**: the pairs whose mesh patch has at most ``FACADE_MAX_HORIZONTAL`` of its faces horizontal
  (the ``frac_horizontal_faces`` cue: walls and steep roofs, where the paper's defects are; the ground and
  flat roofs are left out).
- **Across campuses**: mean and spread (min, max, standard deviation) of each figure over the campuses scored.
"""

from __future__ import annotations

import numpy as np

FACADE_MAX_HORIZONTAL = 0.2
FIGURES = ("ap_bad", "precision_bad", "recall_bad", "f1_bad", "acc", "flagged_share")


def with_flagged(rep: dict) -> dict:
    """``rep`` (a classification report) with "flagged_share": the share of its pairs called bad (on a
    zero-defect case, the false-alarm share: how much of a good mesh repair would rebuild)."""
    cm = np.asarray(rep.get("confusion", [[0, 0], [0, 0]]))
    out = rep | {"flagged_share": float(cm[:, 1].sum() / cm.sum()) if cm.sum() else float("nan")}
    if cm.sum() and not cm[1].sum():  # no labelled bad pair: precision on bad says nothing (0 by definition)
        out |= {"precision_bad": float("nan"), "f1_bad": float("nan")}
    return out


def facade_mask(cues: np.ndarray) -> np.ndarray:
    """(B,) bool: the pairs whose patch is facade-like, from their (B, N_CUES) cues."""
    from ms3d_model.cues import CUE_NAMES

    return np.asarray(cues)[:, CUE_NAMES.index("frac_horizontal_faces")] <= FACADE_MAX_HORIZONTAL


def read_grades(work_dir: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Every tile's stored grades: (patch keys (g,) int64, grade (g,) int8 -1/0/1, score (g,) float32, the
    grader's record of the first tile: {"grader", "model", "threshold", ...})."""
    import json

    import pandas as pd
    import pyarrow.parquet as pq

    from storage.workdir.layout import WorkDir

    wd = WorkDir(work_dir)
    paths = [wd.tile_dir(t) / "grades.parquet" for t in wd.live_tiles()]
    paths = [p for p in paths if p.exists()]
    if not paths:
        return np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.float32), {}
    meta = json.loads((pq.read_schema(paths[0]).metadata or {}).get(b"ms3d", b"{}"))
    d = pd.concat([pd.read_parquet(p, columns=["patch", "grade", "score"]) for p in paths])
    return d["patch"].to_numpy(np.int64), d["grade"].to_numpy(np.int8), d["score"].to_numpy(np.float32), meta


def shipped_scores(work_dir: str, ijk: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict] | None:
    """(flagged (B,) bool, score (B,) float64, grader record) of the shipped path for the pairs at patch
    cells ``ijk`` (B, 3); None when the campus has no stored grades."""
    from storage.grid import PatchGrid

    keys, grade, score, meta = read_grades(work_dir)
    if not len(keys):
        return None
    threshold = float(meta.get("threshold", 0.5))
    order = np.argsort(keys)
    keys, grade, score = keys[order], grade[order], score[order].astype(np.float64)
    want = PatchGrid().pack(np.asarray(ijk, np.int64))
    at = np.clip(np.searchsorted(keys, want), 0, len(keys) - 1)
    found = keys[at] == want
    g = np.where(found, grade[at], -1)
    s = np.where(found, score[at], 0.0)
    flagged = g == 1
    s = np.where(flagged & (s < threshold), 1.0, s)  # lifted to bad by the evidence rule or a user label
    s = np.where(~flagged & (s >= threshold), 0.0, s)  # dropped to good (or unknown) by an override
    return flagged, s, meta


def spread(rows: list[dict], figures: tuple[str, ...] = FIGURES) -> dict:
    """{figure: {"mean", "min", "max", "std", "n"}} over ``rows`` (NaN figures left out)."""
    out = {}
    for k in figures:
        x = np.array([r.get(k, np.nan) for r in rows], np.float64)
        x = x[np.isfinite(x)]
        out[k] = ({"mean": float(x.mean()), "min": float(x.min()), "max": float(x.max()),
                   "std": float(x.std(ddof=1)) if len(x) > 1 else 0.0, "n": int(len(x))} if len(x)
                  else {"mean": float("nan"), "min": float("nan"), "max": float("nan"), "std": float("nan"), "n": 0})
    return out


def spread_table(per_campus: dict[str, dict[str, dict]]) -> str:
    """Text table: one row per (model row, scope) with each figure's mean [min, max] over the campuses.
    per_campus: {campus: {row name: report dict with "all" and "facade" sub-reports}}."""
    rows: dict[tuple[str, str], list[dict]] = {}
    for res in per_campus.values():
        for name, rep in res.items():
            for scope in ("all", "facade"):
                if scope in rep:
                    rows.setdefault((name, scope), []).append(rep[scope])
    width = max([34] + [len(name) for res in per_campus.values() for name in res])
    head = f"{'row':<{width}} {'scope':<7} {'n':>2} " + " ".join(f"{k:>22}" for k in FIGURES)
    lines = [f"Across {len(per_campus)} campuses ({', '.join(per_campus)}): mean [min, max]", head]
    for (name, scope), reps in rows.items():
        s = spread(reps)
        cells = " ".join(f"{v['mean']:>8.3f} [{v['min']:.3f}, {v['max']:.3f}]" if v["n"] else f"{'-':>22}"
                         for v in s.values())
        lines.append(f"{name:<{width}} {scope:<7} {len(reps):>2} {cells}")
    return "\n".join(lines)


__all__ = ["FACADE_MAX_HORIZONTAL", "FIGURES", "with_flagged", "facade_mask", "read_grades", "shipped_scores", "spread", "spread_table"]
