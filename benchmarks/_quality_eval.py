"""The evaluation and tables of ``benchmarks/quality_bench.py``: the truth campus subdivided on its facades,
the facade faces the MLS saw, whole-campus figures per class and scope, and the printed tables."""

from __future__ import annotations

from pathlib import Path

import numpy as np

CLASS_NAMES = ("ground", "road", "wall", "roof", "glass", "frame", "balcony", "eave")
FACADE = (2, 4, 5, 6, 7)


def subdivided_truth(synth: Path, origin: np.ndarray, max_edge_m: float = 0.3):
    """Truth (vertices campus-local, faces, classes) with facade faces split until every edge is <=
    max_edge_m, so per-face masks (MLS-seen) resolve the facade finely; geometry is unchanged."""
    from tasks.quality.truth import load_truth

    tv, tf, tc, _ = load_truth(synth)
    v = tv - origin
    f, c = tf.copy(), tc.copy()
    for _ in range(8):
        e = v[f]
        long = (np.linalg.norm(e - np.roll(e, -1, axis=1), axis=2).max(1) > max_edge_m) & np.isin(c, FACADE)
        if not long.any():
            break
        fl = f[long]
        mids = (v[fl] + v[np.roll(fl, -1, axis=1)]) / 2  # (k, 3, 3): midpoints of edges 01, 12, 20
        base = len(v)
        v = np.concatenate([v, mids.reshape(-1, 3)])
        m = base + np.arange(3 * len(fl)).reshape(-1, 3)
        new = np.concatenate([np.c_[fl[:, 0], m[:, 0], m[:, 2]], np.c_[m[:, 0], fl[:, 1], m[:, 1]],
                              np.c_[m[:, 2], m[:, 1], fl[:, 2]], m])
        f = np.concatenate([f[~long], new])
        c = np.concatenate([c[~long], np.tile(c[long], 4)])
    return v, f, c


def mls_seen(tv, tf, tc, work: Path, radius_m: float = 0.10) -> np.ndarray:
    """(m,) bool: facade faces whose centroid has a registered MLS point within radius_m."""
    from scipy.spatial import cKDTree

    from storage.patches.read import PatchStore
    from storage.workdir.layout import WorkDir
    from tasks.repair.fuse import thin_points

    wd = WorkDir(work)
    pts = []
    for t in wd.live_tiles():
        p, _ = PatchStore(wd.tile_dir(t)).read_all(point_columns=["x", "y", "z"], face_columns=["patch"])
        xyz = np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64)
        pts.append(xyz[thin_points(xyz, 0.03)])
    tree = cKDTree(np.concatenate(pts))
    cen = tv[tf].mean(1)
    d, _ = tree.query(cen, distance_upper_bound=radius_m)
    return np.isfinite(d) & np.isin(tc, FACADE)


def _combine(reports: list) -> dict:
    """Figures of a union of classes from their per-class reports (area-weighted sums, exact)."""
    reports = [r for r in reports if r is not None]
    if not reports:
        return {"F5": float("nan"), "F10": float("nan"), "acc_m": float("nan"), "comp_m": float("nan"),
                "uncovered": float("nan"), "area_m2": 0.0}
    aa = sum(r.accuracy.area_m2 for r in reports)
    ca = sum(r.completeness.area_m2 for r in reports)
    out = {}
    for i, name in enumerate(("F5", "F10")):
        p = sum(r.accuracy.within[i] * r.accuracy.area_m2 for r in reports if r.accuracy.area_m2) / aa if aa else 0.0
        rc = sum(r.completeness.within[i] * r.completeness.area_m2 for r in reports if r.completeness.area_m2) / ca
        out[name] = 2 * p * rc / (p + rc) if p + rc else 0.0
    out["acc_m"] = sum(r.accuracy.mean_m * r.accuracy.area_m2 for r in reports if r.accuracy.area_m2) / aa if aa else float("nan")
    out["comp_m"] = sum(r.completeness.mean_m * r.completeness.area_m2 for r in reports if r.completeness.area_m2) / ca
    ev = sum(r.evaluated_area_m2 for r in reports)
    out["uncovered"] = sum(r.uncovered_area_m2 for r in reports) / ev if ev else float("nan")
    out["area_m2"] = ca
    return out


def evaluate(v, f, truth, seen, spacing_m: float = 0.05) -> dict:
    """Whole-campus figures (``tasks.quality.metrics.evaluate_mesh``, 5 cm samples like ``make demo``).

    One pass with every truth class split into a seen and an unseen copy (a predicted sample takes the
    class of its nearest truth face): "all" is over every facade, "seen" over the facade faces the MLS
    saw (precision from the predicted samples nearest to them, recall and holes over them).
    """
    from tasks.quality.metrics import evaluate_mesh

    tv, tf, tc = truth
    names = CLASS_NAMES + tuple(f"unseen_{n}" for n in CLASS_NAMES)
    cls = np.where(seen, tc, tc + len(CLASS_NAMES))
    r = evaluate_mesh(v, f, tv, tf, spacing_m=spacing_m, taus=(0.05, 0.10), true_face_mask=np.isin(tc, FACADE),
                      true_face_class=cls, class_names=names)
    pc = r.per_class
    facade = [CLASS_NAMES[c] for c in FACADE]
    out = {"all": {**_combine([pc.get(n) for n in facade] + [pc.get(f"unseen_{n}") for n in facade]),
                   "per_class": {n: _combine([pc.get(n), pc.get(f"unseen_{n}")]) for n in facade}},
           "seen": {**_combine([pc.get(n) for n in facade]), "per_class": {n: _combine([pc.get(n)]) for n in facade}},
           "campus": {"F5": r.fscore[0], "F10": r.fscore[1], "acc_m": r.accuracy.mean_m,
                      "comp_m": r.completeness.mean_m, "uncovered": r.uncovered_fraction,
                      "per_class": {n: _combine([pc.get(n), pc.get(f"unseen_{n}")]) for n in CLASS_NAMES
                                    if n in pc or f"unseen_{n}" in pc}}}
    return out


def _campus_classes(results: dict) -> list[str]:
    """Every truth class over the whole campus at 5 decimals, and which classes a variant makes worse than (a)
    (lower F@5cm, or more uncovered facade area)."""
    classes = [c for c in CLASS_NAMES if any(c in r["campus"].get("per_class", {}) for r in results.values())]
    if not classes:
        return []
    out = ["\nper class, whole campus: F@5cm / uncovered (facade classes)",
           "| variant | " + " | ".join(classes) + " |", "|---" * (len(classes) + 1) + "|"]
    for name, r in results.items():
        pc = r["campus"]["per_class"]
        cells = ["-" if c not in pc else f"{pc[c]['F5']:.5f}" + ("" if np.isnan(pc[c]["uncovered"]) else
                                                                 f" / {100 * pc[c]['uncovered']:.2f} %") for c in classes]
        out.append(f"| {name} | " + " | ".join(cells) + " |")
    base = results.get("a", {}).get("campus", {}).get("per_class")
    for name, r in results.items():
        if base is None or name == "a":
            continue
        pc = r["campus"]["per_class"]
        worse = [f"{c} (F@5cm {pc[c]['F5'] - base[c]['F5']:+.2e})" for c in classes if c in pc and c in base
                 and pc[c]["F5"] < base[c]["F5"]]
        worse += [f"{c} (uncovered {100 * (pc[c]['uncovered'] - base[c]['uncovered']):+.3f} points)" for c in classes
                  if c in pc and c in base and pc[c]["uncovered"] > base[c]["uncovered"]]
        out.append(f"({name}) classes worse than (a): " + (", ".join(worse) if worse else "none"))
    return out


def table(results: dict) -> str:
    """Markdown tables: overall figures over all facades and over the MLS-seen ones, then per class."""
    classes = ("wall", "glass", "frame", "balcony", "eave")
    out = []
    for scope, title in (("campus", "whole campus (every class; uncovered: facades)"), ("all", "all facades"),
                         ("seen", "facades the MLS saw")):
        out += [f"\n{title}:", "| variant | F@5cm | F@10cm | accuracy (cm) | completeness (cm) | uncovered |",
                "|---|---|---|---|---|---|"]
        for name, r in results.items():
            a = r[scope]
            out.append(f"| {name} | {a['F5']:.3f} | {a['F10']:.3f} | {100 * a['acc_m']:.2f} | {100 * a['comp_m']:.2f} | "
                       f"{100 * a['uncovered']:.1f} % |")
        if scope == "campus":
            out += _campus_classes(results)
            continue
        out += [f"\nper class, {title}: F@5cm / F@10cm / uncovered",
                "| variant | " + " | ".join(classes) + " |", "|---" * (len(classes) + 1) + "|"]
        for name, r in results.items():
            pc = r[scope]["per_class"]
            cells = [f"{pc[c]['F5']:.3f} / {pc[c]['F10']:.3f} / {100 * (pc[c]['uncovered'] or 0):.1f} %" if c in pc else "-"
                     for c in classes]
            out.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def region_lines(var: str, rows: list[dict]) -> list[str]:
    """One line per region: key, result, defect type, patches, rebuilt faces, wall / CPU seconds, peak RSS."""
    head = (f"({var}) {'region':18} {'result':8} {'type':13} {'patches':>7} {'faces':>8} {'wall s':>7} {'CPU s':>7} "
            f"{'RSS MB':>7} {'gap m':>6}")
    out = [head]
    for r in rows:
        out.append(f"({var}) {r.get('unit', ''):18} {r.get('result', r.get('status', '')):8} "
                   f"{r.get('defect_type', '')!s:13} {r.get('n_patches', 0):7d} {r.get('rebuilt_faces', 0):8d} "
                   f"{r.get('seconds', 0.0):7.1f} {r.get('cpu_seconds', 0.0):7.1f} {r.get('peak_rss_mb', 0.0):7.0f} "
                   f"{(r.get('max_border_gap_m') or 0.0):6.3f}")
    return out


def region_figures(rows: list[dict]) -> dict:
    done = [r for r in rows if r.get("status") == "done"]
    sec = np.array([r.get("seconds", 0.0) for r in done])
    cpu = np.array([r.get("cpu_seconds", 0.0) for r in done])
    rss = np.array([r.get("peak_rss_mb", 0.0) for r in done])
    gaps = [r.get("max_border_gap_m") or 0.0 for r in done]
    types = {}
    for r in done:
        types[r.get("defect_type")] = types.get(r.get("defect_type"), 0) + 1
    return {"regions": len(rows), "done": len(done), "failed": len(rows) - len(done),
            "rebuilt": sum(r.get("result") == "rebuilt" for r in done),
            "seconds_total": float(sec.sum()), "cpu_seconds_total": float(cpu.sum()),
            "seconds_median": float(np.median(sec)) if len(sec) else 0.0,
            "seconds_max": float(sec.max()) if len(sec) else 0.0,
            "peak_rss_mb_max": float(rss.max()) if len(rss) else 0.0,
            "peak_rss_mb_median": float(np.median(rss)) if len(rss) else 0.0,
            "max_border_gap_m": float(max(gaps)) if gaps else 0.0, "defect_types": types}
