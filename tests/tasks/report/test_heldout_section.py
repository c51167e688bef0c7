"""The report's held-out section (``tasks.report.heldout``): the per-building table between the campus and the
tiles, at most ``MAX_BUILDINGS`` rows (most held-out points first, said when there are more), and a document
of before the buildings (no "buildings") laid out as it was."""

from __future__ import annotations

from tasks.report.heldout import MAX_BUILDINGS, heldout_section


def _figures(points: int, median_m: float) -> dict:
    return {"points": points, "median_m": median_m, "p90_m": 2 * median_m, "within_5cm": 0.5, "within_10cm": 0.9}


def _doc(n_buildings: int | None) -> dict:
    doc = {"held_out": 1000, "points": 10000, "held_out_share": 0.1,
           "holdout": {"share": 0.1, "block_s": 1.0, "cell_m": 5.0, "seed": 0},
           "campus": {"input mesh": _figures(1000, 0.03), "merged model": _figures(1000, 0.02)},
           "tiles": {"3_4": {"input mesh": _figures(1000, 0.03), "merged model": _figures(1000, 0.02)}}}
    if n_buildings is not None:
        doc["buildings"] = [{"id": i, "area_m2": 100.0 + i, "height_m": 10.0, "centroid": [0, 0],
                             "centroid_world": [0, 0], "models": {"input mesh": _figures(i, 0.04),
                                                                   "merged model": _figures(i, 0.01)}}
                            for i in range(1, n_buildings + 1)]
        doc["buildings"].append({"id": 0, "name": "other", "models": {"input mesh": _figures(7, 0.03)}})
    return doc


def test_an_old_document_keeps_one_table_of_campus_and_tiles():
    body = heldout_section(_doc(None)).body
    assert body.count("<table>") == 1 and "Per building" not in body
    assert body.index("<td>campus</td>") < body.index("<td>tile 3_4</td>")


def test_buildings_sit_between_the_campus_and_the_tiles_most_points_first():
    body = heldout_section(_doc(3)).body
    assert body.count("<table>") == 3
    assert body.index("<td>campus</td>") < body.index("Per building") < body.index("<td>tile 3_4</td>")
    rows = body[body.index("Per building"):body.index("Per tile")].split("<tr>")[2:]
    assert [r.split("</td>")[0] for r in rows] == ["<td>3", "<td>2", "<td>1", "<td>other (no building)"]
    # both models side by side: input median then merged median; an absent model's figures are blank
    assert rows[0].startswith("<td>3</td><td>103</td><td>10.0</td><td>3</td><td>0.040</td><td>0.080</td>"
                              "<td>0.500</td><td>0.010</td>")
    assert rows[-1].endswith("<td>0.030</td><td>0.060</td><td>0.500</td><td>–</td><td>–</td><td>–</td></tr></table><h3>")
    assert "3 buildings hold" in body and "are shown" not in body


def test_at_most_the_limit_of_buildings_and_says_so():
    body = heldout_section(_doc(MAX_BUILDINGS + 7)).body
    table = body[body.index("Per building"):body.index("Per tile")]
    assert table.count("<tr>") == 1 + MAX_BUILDINGS + 1  # header, the buildings, "other"
    assert f"The {MAX_BUILDINGS} with the most held-out points of {MAX_BUILDINGS + 7} are shown" in table
    assert f"<td>{MAX_BUILDINGS + 7}</td>" in table and "<td>7</td><td>107</td>" not in table
