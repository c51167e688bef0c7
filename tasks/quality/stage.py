"""The quality stage: the merged model (and the input mesh, when regions were rebuilt) measured against a
synth campus's truth, in shares the flow runs side by side, summed into ``report/quality.json``.

The figures are cached under a key of what they depend on (:func:`quality_key`: the merged tiles, the
truth mesh, the parameters), so a rerun with unchanged tiles measures nothing.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import file_fingerprint, file_sha256, write_json_atomic
from storage.contracts.tile_mesh import SOURCE_REBUILT, read_tile_arrays, read_tile_mesh, tile_mesh_paths
from storage.ids import TileId
from storage.patches.read import PatchStore
from storage.patches.schema import PATCHES_FILE, POINTS_FILE
from storage.workdir.layout import WorkDir, campus_frame, read_campus
from storage.workdir.manifest import combine_fingerprints
from tasks.geometry.footprints import CellHeights, Footprints, cell_heights, footprints_of
from tasks.quality.buildings import GroupedSums, building_rows
from tasks.quality.heldout import CAP_M, HeldOutSums, faces_near

QUALITY_VERSION = 2  # 2: the input mesh row is measured on the ingested faces
QUALITY_TILE_M = 25.0  # quality is evaluated tile by tile (memory): distances capped at the buffer
QUALITY_BUFFER_M = 2.0


def truth_dir_of(cfg) -> Path | None:
    """The synth campus folder whose ``truth/`` holds the truth mesh, if the inputs come from one."""
    candidates = []
    if cfg.inputs.labels:
        candidates.append(Path(cfg.inputs.labels).parent.parent)
    candidates += [Path(p).parent for p in cfg.inputs.mesh]
    for c in candidates:
        if (c / "truth").is_dir() and list((c / "truth").glob("truth_mesh*.ply")):
            return c
    return None


def merged_tiles(wd: WorkDir) -> list[str]:
    """Keys ("ix_iy") of the tiles with a merged mesh, sorted (on a bucket: recorded, maybe not downloaded)."""
    return sorted(p.parent.name for p in recorded.glob(wd.root / "tiles", "*/merged.json"))


def any_rebuilt_region(wd: WorkDir, tiles: list[str]) -> bool:
    """Whether any merged tile holds a rebuilt face (the test the report's regions section makes on the meshes),
    from the merge records' ``rebuilt_faces`` when each tile's record has it (nothing downloaded; a rebuilt face
    the weld dropped still counts), else from the meshes."""
    from storage.workdir.manifest import read_stage_records

    recs = read_stage_records(wd, "merge")
    counts = [(recs[k].summary or {}).get("rebuilt_faces") if k in recs else None for k in tiles]
    if all(c is not None for c in counts):
        return any(int(c) > 0 for c in counts)
    return any((read_tile_mesh(wd.root / "tiles" / k).source == SOURCE_REBUILT).any() for k in tiles)


def _merged_fingerprint(wd: WorkDir, tiles: list[str]) -> str:
    h = hashlib.sha256()
    for k in tiles:
        npz, meta = tile_mesh_paths(wd.root / "tiles" / k)
        st = recorded.state(npz)  # on a bucket: what the records say, nothing downloaded
        if st is None:
            raise FileNotFoundError(npz)
        h.update(k.encode() + meta.read_bytes() + str(st.size).encode() + str(st.mtime_ns).encode())
    return h.hexdigest()[:32]


def merged_surface(wd: WorkDir, tiles: list[str], shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The merged tiles as one mesh for quality: (vertices (n, 3) float64 = campus-local + ``shift``,
    faces (m, 3) int64). Each tile's vertices are welded by exact position (merge splits a vertex at
    seams only, every copy at one position), which cuts memory several times on seam-rich meshes."""
    from tasks.geometry.groups import first_of_groups

    vs, fs, off = [], [], 0
    for k in tiles:
        tm = read_tile_mesh(wd.root / "tiles" / k)
        b = tm.vertices.view(np.uint32).astype(np.int64)
        group, first = first_of_groups((b[:, 0] << 32) | b[:, 1], b[:, 2])
        vs.append(tm.vertices[first].astype(np.float64) + shift)
        fs.append(group[tm.faces] + off)
        off += len(first)
    return np.concatenate(vs), np.concatenate(fs)


def ingested_surface(wd: WorkDir, tiles: list[str], shift: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The input mesh as ingest stored it in the tiles' patch stores, as one mesh for quality: (vertices (n, 3)
    float64 = campus-local + ``shift``, faces (m, 3) int64), welded by exact position per tile.

    This is the surface the merged model's retained faces are copied from, in the same triangulation (ingest
    splits long faces: :mod:`tasks.geometry.split`) and the same float32 corners. Quality samples each face by
    its geometry (:mod:`tasks.geometry.sampling`), so a face the repair left alone gets the same samples in
    both rows and the two rows differ only where regions were rebuilt. Measured against the input file
    itself, re-triangulation and float32 alone moved per-class F@5cm by up to 2e-6 on campus 9103."""
    from storage.patches.read import PatchStore
    from tasks.geometry.groups import first_of_groups

    cols = [f"{a}{v}" for v in range(3) for a in "xyz"]
    vs, fs, off = [], [], 0
    for k in tiles:
        tri = PatchStore(wd.root / "tiles" / k).read_all_stacked("faces", cols).reshape(-1, 3)
        b = np.ascontiguousarray(tri).view(np.uint32).astype(np.int64)
        group, first = first_of_groups((b[:, 0] << 32) | b[:, 1], b[:, 2])
        vs.append(tri[first].astype(np.float64) + shift)
        fs.append(group.reshape(-1, 3) + off)
        off += len(first)
    if not vs:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    return np.concatenate(vs), np.concatenate(fs)


def quality_key(wd: WorkDir, truth: Path, tiles: list[str], any_rebuilt: bool, spacing_m: float = 0.10) -> dict:
    """What the cached quality figures depend on (merged tiles, truth, parameters)."""
    return {"version": QUALITY_VERSION, "merged": _merged_fingerprint(wd, tiles), "spacing_m": spacing_m,
            "tile_m": QUALITY_TILE_M, "buffer_m": QUALITY_BUFFER_M,
            "truth": file_sha256(min((truth / "truth").glob("truth_mesh*.ply"))), "rebuilt": any_rebuilt}


MODELS = ("merged model", "input mesh")  # what quality measures: the merged model, the input mesh if rebuilt


def quality_share(wd: WorkDir, truth: Path, origin: np.ndarray, tiles: list[str], any_rebuilt: bool,
                  part: tuple, spacing_m: float = 0.10) -> dict:
    """The mergeable quality sums of one share of the quality tiles (``tasks.quality.tiled.evaluate_tiles``):
    {model name: QualityPartial or None}. Shares run as separate tasks; their sums add up exactly.
    part: (k, n) the k-th of n shares of the tiles, of every model; (k, n, model) of one of :data:`MODELS`
    (a share then reads only that model's mesh). origin: (3,) float64 world metres of the campus frame."""
    from tasks.quality.metrics import facade_mask  # late: open3d loads only where quality is measured
    from tasks.quality.tiled import evaluate_tiles
    from tasks.quality.truth import CLASS_NAMES, load_truth

    tv, tf, tc, t_origin = load_truth(truth)
    models = MODELS if any_rebuilt else MODELS[:1]
    if len(part) > 2:
        models = [m for m in models if m == part[2]]
    kw = {"tile_size_m": QUALITY_TILE_M, "buffer_m": QUALITY_BUFFER_M, "spacing_m": spacing_m,
          "true_face_mask": facade_mask(tc), "true_face_class": tc, "class_names": CLASS_NAMES,
          "part": tuple(part[:2])}
    out = {}
    if MODELS[0] in models:
        v, f = merged_surface(wd, tiles, origin - t_origin)
        out[MODELS[0]] = evaluate_tiles(v, f, tv - t_origin, tf, **kw)[0]
        del v, f
    if MODELS[1] in models:
        v, f = ingested_surface(wd, tiles, origin - t_origin)
        out[MODELS[1]] = evaluate_tiles(v, f, tv - t_origin, tf, **kw)[0]
    return out


def write_quality(wd: WorkDir, key: dict, shares: list[dict]) -> dict:
    """Sum the shares into ``report/quality.json`` (the figures the report page shows):
    {"key": ``key``, "rows": {model name: QualityReport.to_dict()}}."""
    rows = {}
    for name in dict.fromkeys(n for s in shares for n in s):
        parts = [s[name] for s in shares if s.get(name) is not None]
        if parts:
            total = parts[0]
            for p in parts[1:]:
                total = total + p
            rows[name] = total.report().to_dict()
    cache = {"key": key, "rows": rows}
    write_json_atomic(wd.report_dir / "quality.json", cache)
    return cache


def ensure_quality(wd: WorkDir, truth: Path, origin: np.ndarray, tiles: list[str], any_rebuilt: bool,
                   spacing_m: float = 0.10) -> dict:
    """The quality figures of the merged model (and of the input mesh when regions were rebuilt) against the
    truth (see :func:`write_quality`), computed (in this process) when ``report/quality.json`` does not hold
    them already."""
    cache_path = wd.report_dir / "quality.json"
    key = quality_key(wd, truth, tiles, any_rebuilt, spacing_m)
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    if cache.get("key") != key:
        cache = write_quality(wd, key, [quality_share(wd, truth, origin, tiles, any_rebuilt, (0, 1), spacing_m)])
    return cache


def quality_plan(cfg, wd: WorkDir) -> dict | None:
    """What a parallel quality run needs ({"key", "truth", "tiles", "rebuilt", "spacing_m"}), or None when
    there is no truth, no merged tile, or the cache is already up to date (cfg: CampusConfig; the sample
    spacing is ``cfg.report.quality_spacing_m``)."""
    truth = truth_dir_of(cfg)
    tiles = merged_tiles(wd)
    if truth is None or not tiles:
        return None
    rebuilt = any_rebuilt_region(wd, tiles)
    spacing = float(cfg.report.quality_spacing_m)
    key = quality_key(wd, truth, tiles, rebuilt, spacing)
    path = wd.report_dir / "quality.json"
    if path.exists() and json.loads(path.read_text()).get("key") == key:
        return None
    return {"key": key, "truth": str(truth), "tiles": tiles, "rebuilt": rebuilt, "spacing_m": spacing}


def quality_parts(plan: dict | None, n_workers: int) -> list[tuple[int, int, str]]:
    """The shares (k, n, model) the flow runs for ``plan``: about one per worker, each of one model (so a share
    reads one mesh: the merged tiles or the input mesh), none without a plan.

    >>> quality_parts({"tiles": ["0_0"], "rebuilt": True}, 2)
    [(0, 1, 'merged model'), (0, 1, 'input mesh')]
    >>> quality_parts({"tiles": ["0_0"], "rebuilt": False}, 2), quality_parts(None, 3)
    ([(0, 2, 'merged model'), (1, 2, 'merged model')], [])
    """
    if not plan:
        return []
    models = MODELS if plan.get("rebuilt") else MODELS[:1]
    n = max(1, n_workers // len(models))
    return [(k, n, m) for m in models for k in range(n)]


def share_name(part: tuple) -> str:
    """The manifest unit of a quality share.

    >>> share_name((0, 1, "input mesh")), share_name((1, 2))
    ('share-0-of-1-input', 'share-1-of-2')
    """
    return f"share-{part[0]}-of-{part[1]}" + (f"-{part[2].split()[0]}" if len(part) > 2 else "")


def run_quality_share(cfg, wd: WorkDir, plan: dict, part: tuple) -> dict:
    """:func:`quality_share` of ``part`` for a plan of :func:`quality_plan`."""
    origin = campus_frame(read_campus(wd)).origin_array
    return quality_share(wd, Path(plan["truth"]), origin, plan["tiles"], plan["rebuilt"], part,
                         float(plan.get("spacing_m", 0.10)))


# ------------------------------------------------------------------------------ accuracy without truth

HELDOUT_VERSION = 2  # 2: per building (footprints of the input mesh)
HELDOUT_FILE = "holdout.json"
HELDOUT_PAD_M = CAP_M  # faces within this of a tile's held-out points: their distances are exact below it
# building footprints of the per-building figures (tasks.geometry.footprints); pad_m: a facade's scan beside it
FOOTPRINTS = {"cell_m": 1.0, "ground_window_m": 25.0, "min_height_m": 2.5, "min_area_m2": 20.0, "pad_m": 1.5}
_POINT_COLUMNS = ["x", "y", "z", "gps_time", "patch"]
_TRI_COLUMNS = [f"{a}{v}" for v in range(3) for a in "xyz"]


def _neighbour_dirs(wd: WorkDir, tile: str) -> list[Path]:
    t = TileId.from_key(tile)
    return [wd.tile_dir(TileId(t.ix + dx, t.iy + dy)) for dx in (-1, 0, 1) for dy in (-1, 0, 1)]


def _near_triangles(dirs: list[Path], read, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(m, 3, 3) float64 triangles of the tiles ``dirs`` (``read(dir)``: their (k, 3, 3) triangles or None)
    within HELDOUT_PAD_M of the box [lo, hi]; one tile's mesh in memory at a time."""
    parts = []
    for d in dirs:
        tri = read(d)
        if tri is not None and len(tri):
            parts.append(tri[faces_near(tri, lo, hi, HELDOUT_PAD_M)].astype(np.float64))
    return np.concatenate(parts) if parts else np.zeros((0, 3, 3))


def _merged_triangles(tile_dir: Path) -> np.ndarray | None:
    if not tile_mesh_paths(tile_dir)[1].exists():
        return None
    a = read_tile_arrays(tile_dir, ("vertices", "faces"))
    return a["vertices"][a["faces"]]


def _input_triangles(tile_dir: Path) -> np.ndarray | None:
    if not (tile_dir / PATCHES_FILE).exists():
        return None
    return PatchStore(tile_dir).read_all_stacked("faces", _TRI_COLUMNS).reshape(-1, 3, 3)


def _distances(points: np.ndarray, tri: np.ndarray) -> np.ndarray:
    from tasks.geometry.distance import MeshDistance  # late: open3d loads only where distances are measured

    if not len(tri):
        return np.full(len(points), np.inf)
    return MeshDistance(tri.reshape(-1, 3), np.arange(3 * len(tri)).reshape(-1, 3)).query(points)[0]


def campus_footprints(wd: WorkDir, tiles: list[str]) -> Footprints:
    """The building footprints (:data:`FOOTPRINTS`) of the input mesh as ingest stored it in ``tiles``,
    campus-local: each tile's faces reduced to its ground cells' heights, one tile's faces in memory at a time."""
    p = {k: v for k, v in FOOTPRINTS.items() if k not in ("cell_m", "pad_m")}
    cells = [cell_heights(tri, FOOTPRINTS["cell_m"]) for k in tiles
             if (tri := _input_triangles(wd.tile_dir(TileId.from_key(k)))) is not None]
    return footprints_of(CellHeights.merge(cells, FOOTPRINTS["cell_m"]), **p)


def heldout_tile(wd: WorkDir, tile: str, holdout, origin: np.ndarray,
                 footprints: Footprints | None = None) -> tuple[dict, int, int, dict]:
    """One tile's held-out points measured against the input mesh and the merged model (the faces of it and
    its eight neighbours near them): ({model: HeldOutSums}, points of the tile, points held out, {model:
    GroupedSums by building id of ``footprints``, 0: none (all 0 without footprints)})."""
    cols, _ = PatchStore(wd.tile_dir(TileId.from_key(tile))).read_all(point_columns=_POINT_COLUMNS, face_columns=[])
    xyz = np.stack([cols[c] for c in "xyz"], 1).astype(np.float64)
    held = holdout.mask(cols["gps_time"], xyz[:, :2] + origin[:2], cols["patch"])
    p = xyz[held]
    out, by_building = {}, {}
    if len(p):
        lo, hi, dirs = p.min(0), p.max(0), _neighbour_dirs(wd, tile)
        building = (footprints.building_of(p[:, :2], FOOTPRINTS["pad_m"]) if footprints is not None
                    else np.zeros(len(p), np.int32))
        for name, read in (("input mesh", _input_triangles), ("merged model", _merged_triangles)):
            d = _distances(p, _near_triangles(dirs, read, lo, hi))
            out[name], by_building[name] = HeldOutSums.of(d), GroupedSums.of(building, d)
    return out, len(xyz), int(held.sum()), by_building


def heldout_key(cfg, wd: WorkDir, tiles: list[str]) -> dict:
    """What the held-out figures depend on: the strip choice, the merged tiles, the tiles' point stores."""
    stores = combine_fingerprints([f"{k}:{file_fingerprint(wd.tile_dir(TileId.from_key(k)) / POINTS_FILE)}"
                                   for k in tiles])
    return {"version": HELDOUT_VERSION, "holdout": cfg.quality.holdout().to_json(),
            "merged": _merged_fingerprint(wd, tiles), "points": stores, "cap_m": CAP_M, "footprints": FOOTPRINTS}


def heldout_pending(cfg, wd: WorkDir) -> bool:
    """Whether :func:`ensure_heldout` has work: a holdout, merged tiles, and no current ``report/holdout.json``
    (so a rerun with nothing changed launches no task)."""
    tiles = merged_tiles(wd)
    if not cfg.quality.holdout().enabled or not tiles:
        return False
    path = wd.report_dir / HELDOUT_FILE
    return not path.exists() or json.loads(path.read_text()).get("key") != heldout_key(cfg, wd, tiles)


def ensure_heldout(cfg, wd: WorkDir) -> dict:
    """``report/holdout.json``: the held-out strips' distances to the input mesh and to the merged model, per
    tile, for the campus and per building ({"key", "holdout", "points", "held_out", "campus": {model: figures},
    "tiles": {tile: {model: figures}}, "footprints": {parameters, "buildings": how many the input mesh has},
    "buildings": [building with held-out points, then "other"] (:func:`tasks.quality.buildings.building_rows`)}),
    measured tile by tile (memory: a tile and its neighbours' faces near it) unless the file already holds
    them. {"status": "off"} without a holdout or merged tiles."""
    tiles = merged_tiles(wd)
    holdout = cfg.quality.holdout()
    if not holdout.enabled or not tiles:
        return {"status": "off"}
    path = wd.report_dir / HELDOUT_FILE
    key = heldout_key(cfg, wd, tiles)
    if path.exists() and (doc := json.loads(path.read_text())).get("key") == key:
        return doc
    origin = campus_frame(read_campus(wd)).origin_array
    fp = campus_footprints(wd, tiles)
    campus, per_tile, per_building, n_points, n_held = {}, {}, {}, 0, 0
    for k in tiles:
        sums, n, h, by_building = heldout_tile(wd, k, holdout, origin, fp)
        n_points, n_held = n_points + n, n_held + h
        per_tile[k] = {name: s.figures() for name, s in sums.items()}
        for name, s in sums.items():
            campus[name] = campus.get(name, HeldOutSums.empty()) + s
        for name, s in by_building.items():
            per_building.setdefault(name, []).append(s)
    per_building = {name: GroupedSums.merge(parts) for name, parts in per_building.items()}
    doc = {"key": key, "holdout": holdout.to_json(), "points": n_points, "held_out": n_held,
           "held_out_share": round(n_held / n_points, 4) if n_points else None,
           "campus": {name: s.figures() for name, s in campus.items()}, "tiles": per_tile,
           "footprints": {**FOOTPRINTS, "buildings": fp.n}, "buildings": building_rows(fp, per_building, origin)}
    write_json_atomic(path, doc)
    return doc


def run_heldout(cfg, wd: WorkDir) -> dict:
    """:func:`ensure_heldout` as a step's small result (the campus figures, flattened)."""
    doc = ensure_heldout(cfg, wd)
    flat = {f"{m.split()[0]}_{k}": v for m, f in (doc.get("campus") or {}).items() for k, v in f.items()}
    return {"status": "done", "held_out": doc.get("held_out", 0), **flat}


def read_heldout(wd: WorkDir) -> dict | None:
    """The recorded ``report/holdout.json`` (see :func:`ensure_heldout`), or None when there is none."""
    path = wd.report_dir / HELDOUT_FILE
    return json.loads(path.read_text()) if path.exists() else None
