"""The report for a user without truth: grades, their distribution, and why patches are unknown."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from storage.frame import CampusFrame
from storage.grid import PatchGrid
from storage.patches.read import PatchStore
from storage.patches.schema import TileMeta, side_table_path
from storage.patches.write import write_side_table, write_tile_tables
from storage.workdir.layout import WorkDir, write_campus
from tasks.partition import build_tile_tables
from tasks.report.grades import UNKNOWN_REASONS, census_of_stores, grades_section, unknown_reasons

GRID = PatchGrid((2.3, 1.0, 0.7), 20.0)
# cell i along x -> (faces, points) it holds, and the grade classify wrote (-1 for unknown)
CELLS = {0: (2, 5, 0), 1: (0, 3, -1), 2: (1, 0, -1), 3: (1, 1, -1), 4: (2, 4, 1), 5: (2, 4, -1), 6: (3, 6, 0)}
MIN_FACES, MIN_POINTS = 2, 3
EXPECTED = {"no_faces": 1, "no_points": 1, "too_few": 1, "not_graded": 1}


def _cell_data(i: int, n_faces: int, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """n_faces small triangles and n_points points inside cell (i, 0, 0) (campus-local metres)."""
    x0 = 2.3 * i + 0.4
    tri = np.array([[[x0 + 0.1 * f, 0.2, 0.2], [x0 + 0.1 * f + 0.3, 0.2, 0.2], [x0 + 0.1 * f, 0.5, 0.4]]
                    for f in range(n_faces)]).reshape(-1, 3, 3)
    pts = np.array([[x0 + 0.05 * p, 0.6, 0.3] for p in range(n_points)]).reshape(-1, 3)
    return tri, pts


def write_handmade_store(root: Path, with_scores: bool = True, **grades_meta) -> WorkDir:
    """One tile whose patches hold exactly CELLS, a grades table and no labels."""
    tris, pts = zip(*(_cell_data(i, f, p) for i, (f, p, _) in CELLS.items()))
    tri, xyz = np.concatenate(tris), np.concatenate(pts)
    faces = {f"{a}{c}": tri[:, c, k].astype(np.float32) for c in range(3) for k, a in enumerate("xyz")}
    faces |= {f"vid{c}": np.arange(len(tri)) * 3 + c for c in range(3)}
    faces |= {"nx": np.zeros(len(tri)), "ny": np.zeros(len(tri)), "nz": np.ones(len(tri)), "src_face": np.arange(len(tri))}
    points = {a: xyz[:, k].astype(np.float32) for k, a in enumerate("xyz")}
    points["classification"] = np.full(len(xyz), 6, np.uint8)
    frame = CampusFrame(origin=(0.0, 0.0, 0.0), crs="EPSG:32650")
    p_s, f_s, patches = build_tile_tables(points, faces, GRID, frame.origin)
    tile_dir = root / "tiles" / "0_0"
    meta = TileMeta(tile="0_0", patch_size_m=GRID.size_m, crs=frame.crs)
    write_tile_tables(tile_dir, p_s, f_s, patches, meta)
    grade = np.array([CELLS[int(i)][2] for i in patches["i"]], np.int8)
    score = np.where(grade >= 0, np.where(grade == 1, 0.8, 0.1), np.nan).astype(np.float32)
    if with_scores:
        write_side_table(tile_dir, "grades", {"patch": patches["patch"], "score": score, "grade": grade}, meta,
                         **grades_meta)
    wd = WorkDir(root)
    write_campus(wd, frame, {"matrix": np.eye(4).tolist(), "scale": 1.0}, {"name": "handmade"})
    return wd


def test_unknown_reasons_are_counted_exactly_on_a_handmade_store(tmp_path):
    wd = write_handmade_store(tmp_path / "work")
    p = PatchStore(wd.tile_dir(wd.live_tiles()[0])).patches()
    assert sorted(p["i"].tolist()) == sorted(CELLS) and p["n_faces"].sum() == sum(c[0] for c in CELLS.values())
    census = census_of_stores([wd.tile_dir(t) for t in wd.live_tiles()], MIN_FACES, MIN_POINTS)
    assert (census.patches, census.good, census.bad, census.unknown) == (7, 2, 1, 4)
    assert census.reasons == EXPECTED and census.sources == ("grades",)
    assert sum(census.score_counts) == 3 and census.score_counts[2] == 2 and census.score_counts[16] == 1
    assert census.unknown_share == pytest.approx(4 / 7)
    # with the default thresholds the 1-face 1-point patch is a pair: then it is "not graded"
    loose = census_of_stores([wd.tile_dir(t) for t in wd.live_tiles()])
    assert loose.reasons == {"no_faces": 1, "no_points": 1, "too_few": 0, "not_graded": 2}


def test_unknown_reasons_agree_with_what_classify_can_grade():
    from tasks.classify.pairs import gradable_mask

    rng = np.random.default_rng(0)
    nf, npt = rng.integers(0, 4, 500), rng.integers(0, 4, 500)
    grade = np.full(500, -1, np.int8)
    why = unknown_reasons(nf, npt, grade, 2, 2)
    pairs = gradable_mask({"n_faces": nf, "n_points": npt}, 2, 2)
    assert ((why == UNKNOWN_REASONS.index("not_graded")) == pairs).all()
    assert (why >= 0).all()


def test_report_without_labels_shows_grades_and_why_unknown(tmp_path):
    from tasks.config import CampusConfig
    from tasks.report import run_report

    wd = write_handmade_store(tmp_path / "work")
    assert not side_table_path(wd.tile_dir(wd.live_tiles()[0]), "labels").exists()
    cfg = CampusConfig(name="handmade", work_dir=str(wd.root), partition={"min_faces": MIN_FACES, "min_points": MIN_POINTS})
    res = run_report(cfg, wd, quality=False)
    page = Path(res["report"]).read_text()
    assert "Grades: distribution and unknown patches" in res["sections"]
    assert "score_histogram" in res["figures"] and (wd.report_dir / "score_histogram.png").stat().st_size > 5_000
    assert "classify&#x27;s grades" in page or "classify's grades" in page
    for reason, n in EXPECTED.items():
        assert f"<tr><td>{reason}</td><td>{n}</td><td>14.3 %</td>" in page, reason
    assert "<tr><td>unknown</td><td>4</td><td>57.1 %</td></tr>" in page
    assert "report.max_unknown_share" in page  # 57 % unknown is above the default 0.5
    cfg2 = cfg.model_copy(update={"report": cfg.report.model_copy(update={"max_unknown_share": 0.6})})
    assert "report.max_unknown_share" not in Path(run_report(cfg2, wd, quality=False)["report"]).read_text()


def test_section_without_grades_says_so(tmp_path):
    wd = write_handmade_store(tmp_path / "work", with_scores=False)
    census = census_of_stores([wd.tile_dir(t) for t in wd.live_tiles()])
    assert census.unknown == census.patches == 7 and census.sources == ("none",)
    assert census.reasons == {"no_faces": 1, "no_points": 1, "too_few": 0, "not_graded": 5}
    sec = grades_section(census, 1, 1)
    assert not sec.figures and "No scores" in sec.body


def test_summary_warns_in_one_line_when_most_patches_are_unknown(tmp_path):
    from flows.summary import format_summary, grades_summary, summarise

    wd = write_handmade_store(tmp_path / "work")
    campus = __import__("json").loads(wd.campus_json.read_text())
    frame = CampusFrame(origin=(0.0, 0.0, 0.0), crs="EPSG:32650")
    for share, warned in ((0.5, True), (0.6, False)):
        snap = {"name": "handmade", "partition": {"min_faces": MIN_FACES, "min_points": MIN_POINTS},
                "report": {"max_unknown_share": share}}
        write_campus(wd, frame, campus["registration"], snap)
        g = grades_summary(wd)
        assert (g["patches"], g["unknown"], g["reasons"]) == (7, 4, EXPECTED)
        text = format_summary(summarise(wd, 1.0, {}, {}))
        lines = [ln for ln in text.splitlines() if ln.startswith("WARNING")]
        assert len(lines) == int(warned), text
        if warned:
            assert "57% of the 7 patches" in lines[0] and "no faces 1, no points 1, too few 1, not graded 1" in lines[0]
    assert grades_summary(WorkDir(tmp_path / "empty")) == {}


def test_the_grades_name_the_model_that_graded(tmp_path):
    """The report credits the grader classify recorded (the shipped default is the trees), never a fixed name;
    a store graded before the grader was recorded names its checkpoint file."""
    wd = write_handmade_store(tmp_path / "trees", grader="GBM trees (default.pt) + the evidence rule",
                              model="default.pt")
    census = census_of_stores([wd.tile_dir(t) for t in wd.live_tiles()])
    assert census.graders == ("GBM trees (default.pt) + the evidence rule",)
    body = grades_section(census, 1, 1).body
    assert "GBM trees (default.pt) + the evidence rule" in body and "MS3DQE" not in body
    old = write_handmade_store(tmp_path / "old", model="ms3dqe_geo.pt")
    assert census_of_stores([old.tile_dir(t) for t in old.live_tiles()]).graders == ("ms3dqe_geo.pt",)


def test_classify_records_the_kind_and_file_of_its_checkpoint():
    from tasks.classify import load_model

    assert load_model(None).label == "GBM trees (default.pt)"  # the shipped default
