"""Before/after renders of the rebuilt regions for the run report.

For each rebuilt region (faces of the merged tiles with source "rebuilt"), the faces around it are drawn
twice with one camera: the input mesh from the patch stores (bad patches red) and the merged model
(rebuilt faces orange). Only the merged tiles near the region and the store patches whose boxes meet it
are read. The renders are returned as the section's figures (``stage.py`` writes them).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.contracts.tile_mesh import SOURCE_REBUILT, read_tile_arrays
from storage.errors import InputError
from storage.grid import PatchGrid
from storage.ids import TileId
from storage.patches.read import PatchStore
from tasks.report.figures import BAD_COLOUR, MESH_COLOUR, REBUILT_COLOUR, render_png, view_basis
from tasks.report.html import Section, table

MAX_REGION_RENDERS = 12
REGION_MARGIN_M = 1.5
_DRAWN = ("vertices", "faces", "source", "region")  # what the renders read of a merged tile


def _region_boxes(tiles_dir: Path, tiles: list[str]) -> dict[int, dict]:
    """Per rebuilt region: bbox of its faces (campus-local), face count, normals sample, tiles."""
    out: dict[int, dict] = {}
    for k in tiles:
        tm = read_tile_arrays(tiles_dir / k, _DRAWN)
        rebuilt = np.flatnonzero(tm["source"] == SOURCE_REBUILT)
        if not len(rebuilt):
            continue
        order = np.argsort(tm["region"][rebuilt], kind="stable")  # each region's faces in face order
        by_region = rebuilt[order]
        regions, starts = np.unique(tm["region"][by_region], return_index=True)
        for r, a, b in zip(regions.tolist(), starts.tolist(), [*starts[1:].tolist(), len(by_region)]):
            tri = tm["vertices"][tm["faces"][by_region[a:b]]].astype(np.float64)
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            rec = out.setdefault(int(r), {"lo": np.full(3, np.inf), "hi": np.full(3, -np.inf), "faces": 0,
                                          "normal": np.zeros(3), "tiles": []})  # fmt: skip
            rec["lo"] = np.minimum(rec["lo"], tri.reshape(-1, 3).min(axis=0))
            rec["hi"] = np.maximum(rec["hi"], tri.reshape(-1, 3).max(axis=0))
            rec["faces"] += len(tri)
            rec["normal"] += n.sum(axis=0)
            rec["tiles"].append(k)
    return out


def _in_box(tri: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    c = tri.mean(axis=1)
    return ((c >= lo) & (c <= hi)).all(axis=1)


def regions_section(tiles_dir: Path, tiles: list[str], grid: PatchGrid, origin: np.ndarray) -> tuple[Section, bool]:
    """Before/after renders (figures "region_<id>") of the largest rebuilt regions of the merged ``tiles``
    under ``tiles_dir`` (``work_dir/tiles``), and whether any region was rebuilt.
    origin: (3,) float64 world metres of the campus frame."""
    sec = Section("Rebuilt regions: before and after")
    boxes = _region_boxes(tiles_dir, tiles)
    if not boxes:
        sec.body = "<p>No rebuilt region in the merged tiles (repair has not run, or found nothing to rebuild).</p>"
        return sec, False
    shown = sorted(boxes, key=lambda r: -boxes[r]["faces"])[:MAX_REGION_RENDERS]
    rows = []
    kept: dict[str, tuple] = {}

    def merged(key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A merged tile's (triangles (m, 3, 3) float32, rebuilt (m,) bool, centroids (m, 3) float32), read
        once while it is among the last two tiles read."""
        if key not in kept:
            while len(kept) >= 2:
                kept.pop(next(iter(kept)))
            tm = read_tile_arrays(tiles_dir / key, _DRAWN)
            tri = tm["vertices"][tm["faces"]]
            kept[key] = (tri, tm["source"] == SOURCE_REBUILT, (tri[:, 0] + tri[:, 1] + tri[:, 2]) / np.float32(3))
        return kept[key]

    for r in shown:
        b = boxes[r]
        lo, hi = b["lo"] - REGION_MARGIN_M, b["hi"] + REGION_MARGIN_M
        before_tri, before_col, after_tri, after_col = [], [], [], []
        near = {TileId.from_key(k) for k in tiles} & set(_tiles_for_box(grid, origin, lo, hi))
        for t in sorted(near):
            tri, rebuilt, centre = merged(t.key)
            sel = ((centre >= lo) & (centre <= hi)).all(axis=1)
            after_tri.append(tri[sel])
            after_col.append(np.where(rebuilt[sel][:, None], REBUILT_COLOUR, MESH_COLOUR))
            tri_b, bad = _store_faces_in_box(tiles_dir / t.key, lo, hi)
            before_tri.append(tri_b)
            before_col.append(np.where(bad[:, None], BAD_COLOUR, MESH_COLOUR))
        before, after = np.concatenate(before_tri), np.concatenate(after_tri)
        basis = view_basis(b["normal"][None, :])
        png = render_png([("before: input mesh, bad patches red", before, np.concatenate(before_col)),
                          ("after: merged, rebuilt faces orange", after, np.concatenate(after_col))], basis,
                         f"region {r}: {b['faces']:,} rebuilt faces in tiles {', '.join(b['tiles'])}")  # fmt: skip
        name = f"region_{r:06d}"
        sec.figures[name] = png
        rows.append([r, b["faces"], " × ".join(f"{v:.1f}" for v in b["hi"] - b["lo"]), ", ".join(b["tiles"])])
    sec.body = table(["region", "rebuilt faces", "extent (m)", "tiles"], rows)
    if len(boxes) > len(shown):
        sec.body += f"<p>{len(boxes) - len(shown)} smaller regions not rendered.</p>"
    return sec, True


def _tiles_for_box(grid: PatchGrid, origin: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> list[TileId]:
    return [TileId(int(a), int(b)) for a, b in grid.tiles_for_bounds(lo + origin, hi + origin)]


def _store_faces_in_box(tile_dir: Path, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The input mesh faces of a tile store with centroids in [lo, hi]: (triangles (k, 3, 3), bad (k,) bool),
    reading only the patches whose boxes meet it."""
    try:
        store = PatchStore(tile_dir)
    except InputError:
        return np.zeros((0, 3, 3), np.float32), np.zeros(0, bool)
    p = store.patches()
    meets = ((p["xmax"] >= lo[0]) & (p["xmin"] <= hi[0]) & (p["ymax"] >= lo[1]) & (p["ymin"] <= hi[1])
             & (p["zmax"] >= lo[2]) & (p["zmin"] <= hi[2]) & (p["n_faces"] > 0))  # fmt: skip
    grades = store.side("grades")
    labels = store.side("labels")
    bad_patch = (grades["grade"] == 1) if grades is not None else (labels["label"] == 1) if labels is not None \
        else np.zeros(len(p["patch"]), bool)
    keys = p["patch"][meets]
    if not len(keys):
        return np.zeros((0, 3, 3), np.float32), np.zeros(0, bool)
    cols = [f"{a}{v}" for v in range(3) for a in "xyz"]
    parts = store.read_patches(keys.tolist(), point_columns=[], face_columns=cols)
    tri = np.concatenate([d.triangles() for d in parts])
    bad = np.repeat(bad_patch[meets], [d.n_faces for d in parts])
    sel = _in_box(tri, lo, hi)
    return tri[sel], bad[sel]
