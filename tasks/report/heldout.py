"""The report's section on accuracy without truth: the held-out MLS strips' distances to the input mesh and to
the merged model (the quality stage's ``report/holdout.json``), for the campus and per tile. Pure."""

from __future__ import annotations

from tasks.report.html import Section, table

MODELS = ("input mesh", "merged model")
_HEADER = ["", "model", "held-out points", "median (m)", "p90 (m)", "within 5 cm", "within 10 cm"]


def _rows(where: str, figures: dict) -> list[list]:
    return [[where, m, f["points"], f["median_m"], f["p90_m"], f["within_5cm"], f["within_10cm"]]
            for m in MODELS if (f := figures.get(m))]


def heldout_section(doc: dict | None) -> Section:
    """The section of ``doc`` (``report/holdout.json``), or why there is none."""
    sec = Section("Accuracy without truth: held-out MLS strips")
    if not doc or not doc.get("campus"):
        sec.body = ("<p>No held-out MLS (quality.holdout_share is 0, or no merged tile yet).</p>" if not doc else
                    "<p>No MLS point was held out (too few strips, or no points).</p>")
        return sec
    h = doc["holdout"]
    rows = _rows("campus", doc["campus"])
    for tile, figures in sorted(doc.get("tiles", {}).items()):
        rows += _rows(f"tile {tile}", figures)
    sec.body = (f"<p>{doc['held_out']:,} of {doc['points']:,} MLS points ({100 * (doc.get('held_out_share') or 0):.1f} %) "
                f"were held out of the repair: whole strips of {h['block_s']:g} GPS seconds ({h['cell_m']:g} m ground "
                f"cells without time), share {h['share']:g}, seed {h['seed']}. Their distance to each model measures it "
                "on points that shaped neither; distances beyond 1 m count as 1 m.</p>" + table(_HEADER, rows))
    return sec


__all__ = ["heldout_section"]
