"""The report's section on accuracy without truth: the held-out MLS strips' distances to the input mesh and to
the merged model (the quality stage's ``report/holdout.json``), for the campus, per building (where the file
has them) and per tile. Pure."""

from __future__ import annotations

from tasks.report.html import Section, esc, table

MODELS = ("input mesh", "merged model")
MAX_BUILDINGS = 50  # rows of the building table: the buildings with the most held-out points
_HEADER = ["", "model", "held-out points", "median (m)", "p90 (m)", "within 5 cm", "within 10 cm"]
_BUILDING_HEADER = ["building", "footprint (m²)", "height (m)", "held-out points",
                    *(f"{m.split()[0]} {k}" for m in MODELS for k in ("median (m)", "p90 (m)", "within 5 cm"))]


def _rows(where: str, figures: dict) -> list[list]:
    return [[where, m, f["points"], f["median_m"], f["p90_m"], f["within_5cm"], f["within_10cm"]]
            for m in MODELS if (f := figures.get(m))]


def _points(b: dict) -> int:
    return max((f.get("points") or 0 for f in b.get("models", {}).values()), default=0)


def _building_row(b: dict) -> list:
    figs = [b.get("models", {}).get(m) or {} for m in MODELS]
    name = "other (no building)" if not b.get("id") else b["id"]
    area, height = b.get("area_m2"), b.get("height_m")
    return [name, None if area is None else f"{area:,.0f}", None if height is None else f"{height:.1f}", _points(b),
            *(f.get(k) for f in figs for k in ("median_m", "p90_m", "within_5cm"))]


def buildings_table(buildings: list[dict], footprints: dict | None = None, limit: int = MAX_BUILDINGS) -> str:
    """The per-building table of ``report/holdout.json``'s "buildings" (and "footprints": the parameters): the
    ``limit`` buildings with the most held-out points (most first), then the points on no building; the two
    models side by side."""
    ranked = sorted((b for b in buildings if b.get("id")), key=lambda b: (-_points(b), b["id"]))
    other = [b for b in buildings if not b.get("id")]
    more = (f" The {limit} with the most held-out points of {len(ranked)} are shown." if len(ranked) > limit
            else "")
    p = {"min_height_m": 2.5, "min_area_m2": 20.0, "pad_m": 1.5, **(footprints or {})}
    n = f"{len(ranked)} building holds" if len(ranked) == 1 else f"{len(ranked):,} buildings hold"
    intro = (f"<h3>Per building</h3><p>{n} held-out points. Buildings are the footprints "
             f"of the input mesh: ground cells more than {p['min_height_m']:g} m above the ground, at least "
             f"{p['min_area_m2']:g} m² each; a point within {p['pad_m']:g} m of one (its facade) counts as "
             f"it.{esc(more)}</p>")
    return intro + table(_BUILDING_HEADER, [_building_row(b) for b in ranked[:limit] + other])


def heldout_section(doc: dict | None) -> Section:
    """The section of ``doc`` (``report/holdout.json``), or why there is none."""
    sec = Section("Accuracy without truth: held-out MLS strips")
    if not doc or not doc.get("campus"):
        sec.body = ("<p>No held-out MLS (quality.holdout_share is 0, or no merged tile yet).</p>" if not doc else
                    "<p>No MLS point was held out (too few strips, or no points).</p>")
        return sec
    h = doc["holdout"]
    rows = _rows("campus", doc["campus"])
    tile_rows = [r for tile, figures in sorted(doc.get("tiles", {}).items()) for r in _rows(f"tile {tile}", figures)]
    if doc.get("buildings"):  # campus, buildings, tiles
        tables = (table(_HEADER, rows) + buildings_table(doc["buildings"], doc.get("footprints"))
                  + ("<h3>Per tile</h3>" + table(_HEADER, tile_rows) if tile_rows else ""))
    else:
        tables = table(_HEADER, rows + tile_rows)
    sec.body = (f"<p>{doc['held_out']:,} of {doc['points']:,} MLS points ({100 * (doc.get('held_out_share') or 0):.1f} %) "
                f"were held out of the repair: whole strips of {h['block_s']:g} GPS seconds ({h['cell_m']:g} m ground "
                f"cells without time), share {h['share']:g}, seed {h['seed']}. Their distance to each model measures it "
                "on points that shaped neither; distances beyond 1 m count as 1 m.</p>" + tables)
    return sec


__all__ = ["buildings_table", "heldout_section"]
