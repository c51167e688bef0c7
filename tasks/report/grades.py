"""What the grader said, for a user without truth: the grade distribution and why patches went ungraded.

The classify stage grades a patch only when it is a pair: at least ``partition.min_faces`` faces and
``partition.min_points`` points (``tasks.classify.pairs.gradable_mask``). Every other patch is unknown
(grade -1), for one of these reasons, checked in this order:

- ``no_faces``: points but no face (the mesh lacks the surface, or cars, people, vegetation);
- ``no_points``: faces but no point (roofs, courtyards: what a street scanner cannot see);
- ``too_few``: both, but fewer than the thresholds;
- ``not_graded``: a pair, but no grade (classify has not run on the tile, or is disabled).

:func:`unknown_reasons` and :func:`grade_census` are pure (arrays in); :func:`census_of_stores` reads the
patches tables and the grades side tables (``storage.patches.state.patch_grades``, mode "auto": classify's
grades, else the labels); :func:`grades_section` renders the census for ``report.html``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.patches.read import PatchTable, read_side_table
from storage.patches.state import patch_grades
from tasks.report.figures import score_histogram_png
from tasks.report.html import Section, esc, table

UNKNOWN_REASONS = ("no_faces", "no_points", "too_few", "not_graded")
REASON_TEXT = {
    "no_faces": "points but no mesh face (the mesh lacks the surface, or cars, people, vegetation)",
    "no_points": "mesh faces but no MLS point (roofs, courtyards: what the scanner cannot see)",
    "too_few": "both, but fewer than partition.min_faces / min_points",
    "not_graded": "a pair, but no grade (classify has not run on the tile, or is disabled)",
}
SCORE_BINS = 20


def unknown_reasons(n_faces: np.ndarray, n_points: np.ndarray, grade: np.ndarray, min_faces: int = 1,
                    min_points: int = 1) -> np.ndarray:
    """Why each patch is unknown: (u,) int8 index into ``UNKNOWN_REASONS``, -1 for a graded patch.

    n_faces, n_points: (u,) int counts per patch; grade: (u,) int8 (-1 unknown, 0 good, 1 bad).

    >>> unknown_reasons(np.array([0, 3, 1, 2, 2]), np.array([5, 0, 1, 9, 9]), np.array([-1, -1, -1, -1, 0]),
    ...                 min_faces=2).tolist()
    [0, 1, 2, 3, -1]
    """
    n_faces, n_points, grade = np.asarray(n_faces), np.asarray(n_points), np.asarray(grade)
    gradable = (n_faces >= max(min_faces, 1)) & (n_points >= max(min_points, 1))
    reason = np.select([n_faces == 0, n_points == 0, ~gradable], [0, 1, 2], default=3).astype(np.int8)
    return np.where(grade < 0, reason, -1).astype(np.int8)


@dataclass(frozen=True)
class GradeCensus:
    """Counts of patches by grade and unknown reason, and the histogram of the scores.

    score_counts: (SCORE_BINS,) int64 over [0, 1] (graded patches with a finite score); sources: the
    tables the grades came from ("grades", "labels", "none"), sorted; graders: what graded the stores whose
    grades came from classify (its ``grader`` metadata, e.g. "GBM trees (default.pt) + the evidence rule"), sorted."""

    patches: int
    good: int
    bad: int
    unknown: int
    reasons: dict[str, int]
    score_counts: tuple[int, ...]
    sources: tuple[str, ...] = field(default=())
    graders: tuple[str, ...] = field(default=())

    @property
    def unknown_share(self) -> float:
        return self.unknown / self.patches if self.patches else 0.0

    def to_json(self) -> dict:
        return {"patches": self.patches, "good": self.good, "bad": self.bad, "unknown": self.unknown,
                "unknown_share": self.unknown_share, "reasons": dict(self.reasons), "sources": list(self.sources)}


def grade_census(n_faces: np.ndarray, n_points: np.ndarray, grade: np.ndarray, score: np.ndarray | None = None,
                 min_faces: int = 1, min_points: int = 1, sources: tuple[str, ...] = (),
                 graders: tuple[str, ...] = ()) -> GradeCensus:
    """The census of patches with these counts and grades ((u,) arrays; score (u,) float or None).

    >>> c = grade_census(np.array([0, 3, 2, 2]), np.array([5, 0, 9, 9]), np.array([-1, -1, 0, 1]),
    ...                  np.array([np.nan, np.nan, 0.1, 0.9]))
    >>> c.good, c.bad, c.unknown, c.reasons["no_faces"], c.reasons["no_points"], sum(c.score_counts)
    (1, 1, 2, 1, 1, 2)
    """
    grade = np.asarray(grade)
    why = unknown_reasons(n_faces, n_points, grade, min_faces, min_points)
    counts = np.bincount(why[why >= 0], minlength=len(UNKNOWN_REASONS))
    hist = np.zeros(SCORE_BINS, np.int64)
    if score is not None:
        s = np.asarray(score, np.float64)[grade >= 0]
        hist = np.histogram(s[np.isfinite(s)], bins=SCORE_BINS, range=(0.0, 1.0))[0]
    return GradeCensus(len(grade), int((grade == 0).sum()), int((grade == 1).sum()), int((grade < 0).sum()),
                       {r: int(n) for r, n in zip(UNKNOWN_REASONS, counts)}, tuple(int(v) for v in hist),
                       tuple(sorted(set(sources))), tuple(sorted(set(graders))))


def census_of_stores(tile_dirs: list[Path], min_faces: int = 1, min_points: int = 1) -> GradeCensus:
    """The census over the stores in ``tile_dirs`` (grades as ``repair.grades: auto`` reads them)."""
    nf, npt, gr, sc, sources, graders = [], [], [], [], [], []
    for tile_dir in tile_dirs:
        store = PatchTable(tile_dir)  # the patches and side tables only (on a bucket: all it downloads)
        p = store.patches()
        _, grade, source = patch_grades(store, "auto")
        got = read_side_table(tile_dir, "grades", p["patch"]) if source == "grades" else None
        side = None if got is None else got[0]
        if got is not None:  # stores graded before the grader was recorded name the checkpoint file
            graders.append(got[1].get("grader") or got[1].get("model") or "the grader")
        nf.append(p["n_faces"])
        npt.append(p["n_points"])
        gr.append(grade)
        sc.append(side["score"] if side is not None else np.full(len(grade), np.nan, np.float32))
        sources.append(source)
    if not gr:
        return grade_census(np.zeros(0), np.zeros(0), np.zeros(0, np.int8))
    cat = np.concatenate
    return grade_census(cat(nf), cat(npt), cat(gr), cat(sc), min_faces, min_points, tuple(sources), tuple(graders))


def _share(n: int, total: int) -> str:
    return f"{100 * n / total:.1f} %" if total else "–"


def grades_section(census: GradeCensus, min_faces: int, min_points: int, threshold: float = 0.5,
                   max_unknown_share: float = 0.5) -> Section:
    """The grade distribution, the unknown patches by reason, and the score histogram (figure
    "score_histogram")."""
    sec = Section("Grades: distribution and unknown patches")
    c, n = census, census.patches
    if not n:
        sec.body = "<p>No patch stores.</p>"
        return sec
    src = {"grades": f"classify's grades ({'; '.join(c.graders) or 'the grader'})", "labels": "the labels (truth)",
           "none": "none"}
    sec.body = (f"<p>Grades from {esc(', '.join(src.get(s, s) for s in c.sources) or 'none')} over "
                f"{n:,} patches.</p>")
    sec.body += table(["grade", "patches", "share"], [["good", c.good, _share(c.good, n)],
                                                      ["bad", c.bad, _share(c.bad, n)],
                                                      ["unknown", c.unknown, _share(c.unknown, n)]])  # fmt: skip
    sec.body += "<h3>Why patches are unknown</h3>" + table(
        ["reason", "patches", "share of all", "meaning"],
        [[r, c.reasons[r], _share(c.reasons[r], n), REASON_TEXT[r]] for r in UNKNOWN_REASONS])
    sec.body += (f"<p>A patch is graded when it holds at least {min_faces} face(s) and {min_points} point(s) "
                 "(<code>partition.min_faces</code> / <code>min_points</code>).</p>")
    if c.unknown_share > max_unknown_share:
        sec.body += (f"<p class='note'>{_share(c.unknown, n)} of the patches are unknown (more than "
                     f"<code>report.max_unknown_share</code> = {max_unknown_share:g}): most of the model was not "
                     "judged against the MLS points.</p>")
    if sum(c.score_counts):
        sec.figures["score_histogram"] = score_histogram_png(np.asarray(c.score_counts), threshold)
    else:
        sec.body += "<p>No scores (no patch was graded by the network).</p>"
    return sec
