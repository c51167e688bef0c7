"""The export stage: plan the quadtree over the merged tiles, build the nodes whose fingerprint changed
(here, in a process pool, or mapped by the flow), write the small JSON files, record it in the manifest.

Output (``work_dir/output``)::

    tileset.json                  3D Tiles 1.1: a quadtree over the ground tiles, refine REPLACE, root
                                  ``transform`` = float64 ENU->ECEF (column-major)
    content/tiles/{ix}_{iy}.glb   leaves: full resolution, textured + vertex-coloured primitives
    content/lod{h}/{x}_{y}.glb    parents h levels above the leaves: decimated, vertex-coloured
    overview.glb                  the whole campus decimated, same ENU frame (y-up glTF)
    georef.json                   source CRS, origin, vertical datum, ENU origin, the PROJ operation and
                                  what was assumed
    points/tileset.json, *.glb    the registered MLS points, thinned, as POINTS in the same frame (an
                                  overlay for the viewer, ``points.py``, ``overlay.py``; only when the tiles have stores)
    tileset.fingerprints.json     per node: input fingerprint, box, geometric error (for reruns)
    (work_dir/export/lod/*.npz    per node: the decimated mesh it passes to its parent)

Every face carries grade / source / region as EXT_mesh_features + EXT_structural_metadata.

Memory is bounded by a tile: a leaf is converted alone; a parent reads its children's passed-up meshes
(each decimated by ``lod_reduction``), welds them, and passes up its own decimation. A rerun rebuilds a
node only when its fingerprint (its inputs' content hashes, the parameters and the georeference)
changed: one changed tile rewrites that tile's content and its ancestors, nothing else.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import write_bytes_atomic, write_json_atomic
from storage.errors import InputError
from storage.patches.state import store_fingerprint
from storage.workdir.layout import WorkDir, campus_frame, read_campus
from tasks.batches import balanced_batches
from tasks.config import ExportConfig
from tasks.export.georef import GeoRef, make_georef
from tasks.export.nodes import NodeJob, build_node, content_hash, leaf_fingerprint
from tasks.export.overlay import PointsJob, build_points, write_points_overlay
from tasks.export.tree import EXPORT_VERSION, QuadNode, QuadTree, plan_quadtree, tileset_json
from tasks.units import failure_message, record_step

OVERVIEW = QuadNode(-1, 0, 0)

# ------------------------------------------------------------------------------------- the export run


def _enu_centre(campus: dict, origin: np.ndarray, tiles: list[str]) -> tuple[float, float, float]:
    """Centre of the tiles' footprint (campus-local metres, z 0): the origin of the ENU frame."""
    ij = np.array([[int(v) for v in k.split("_")] for k in tiles], np.float64)
    mid = (ij.min(axis=0) + ij.max(axis=0) + 1) / 2
    if "grid" in campus:  # a pipeline work dir: tile keys are world-anchored (storage.grid), not origin-relative
        grid = campus["grid"]
        centre = mid * float(grid["tile_size_m"]) + np.asarray(grid["anchor_m"][:2], np.float64) - origin[:2]
    else:
        centre = mid * float(campus.get("config", {}).get("tiling", {}).get("tile_size_m", 100.0))
    return float(centre[0]), float(centre[1]), 0.0


def _run_jobs(jobs: list[NodeJob], workers: int) -> list[dict]:
    """:func:`build_node` on each job, in order; side by side in a forkserver pool when workers > 1."""
    if workers <= 1 or len(jobs) <= 1:
        return [build_node(j) for j in jobs]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    ctx = multiprocessing.get_context("forkserver")
    with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx) as pool:
        return list(pool.map(build_node, jobs))


def _build_tree(tree: QuadTree, tiles_dir: Path, template: NodeJob, old: dict[str, dict],
                run: Callable[[list[NodeJob]], list[dict]]) -> tuple[dict[str, dict], list[str], list[str]]:
    """Every node's record, level by level from the leaves: reused from ``old`` when its fingerprint and
    files are unchanged, else built by ``run``. Returns (records by key, keys built, keys reused)."""
    base = template.fingerprint
    nodes: dict[str, dict] = {}
    built, reused = [], []
    for level in tree.levels:
        jobs = []
        for n in level:
            if n.h == 0:
                tile_dir = tiles_dir / tree.leaf_tile[n]
                job = replace(template, node=n, fingerprint=leaf_fingerprint(tile_dir, base), tile_dir=tile_dir)
            else:
                kids = tuple((c.key, nodes[c.key]) for c in tree.children[n])
                job = replace(template, node=n, fingerprint=content_hash(base, [r["fingerprint"] for _, r in kids]),
                              children=kids)
            rec = old.get(n.key)  # its files on a bucket: recorded, maybe not downloaded (storage.recorded)
            if rec and rec["fingerprint"] == job.fingerprint and recorded.is_file(job.out / rec["uri"]) \
                    and recorded.is_file(job.cache / f"{n.key}.npz"):
                nodes[n.key] = rec
                reused.append(n.key)
            else:
                jobs.append(job)
        for job, rec in zip(jobs, run(jobs) if jobs else []):
            nodes[job.node.key] = rec
            built.append(job.node.key)
    return nodes, built, reused


def _write_tileset(out: Path, doc: dict, georef: GeoRef, nodes: dict[str, dict]) -> Path:
    """tileset.json (rewritten only when its bytes change), georef.json and tileset.fingerprints.json."""
    text = (json.dumps(doc, indent=1) + "\n").encode()
    tileset = out / "tileset.json"
    if not tileset.exists() or tileset.read_bytes() != text:
        write_bytes_atomic(tileset, text)
    write_json_atomic(out / "georef.json", georef.to_json())
    write_json_atomic(out / "tileset.fingerprints.json", {"version": EXPORT_VERSION, "nodes": nodes})
    return tileset


def _remove_stale(out: Path, cache: Path, nodes: dict[str, dict]) -> None:
    """Remove the content glbs and cached LOD meshes that no node of the plan names."""
    named = {rec["uri"] for rec in nodes.values()}
    for stale in recorded.glob(out / "content", "**/*.glb"):
        if stale.relative_to(out).as_posix() not in named:
            recorded.unlink(stale)
    for stale in recorded.glob(cache, "*.npz"):
        if stale.stem not in nodes:
            recorded.unlink(stale)


def run_export(work_dir: str | Path, config: ExportConfig | None = None, tiles: list[str] | None = None,
               workers: int = 1, map_jobs: Callable[[list[NodeJob]], list[dict]] | None = None) -> dict:
    """Write ``work_dir/output`` (see the module docstring) from ``tiles/*/merged.npz``.

    tiles: tile keys to export (default: every tile with a merged mesh). workers: processes building
    the nodes of one level side by side (1 inside a Dask worker, whose daemon process may not fork a
    pool; memory grows to ``workers`` tiles). map_jobs: instead, a callable ``(jobs) -> records`` that
    runs :func:`build_node` on every job (in order), e.g. as tasks mapped over a cluster; this function
    then only plans, and writes the small JSON files. Returns a summary: nodes built / reused, faces,
    bytes, seconds, the paths written.
    """
    t0 = time.perf_counter()
    cfg = config or ExportConfig()
    wd = WorkDir(work_dir)
    out, cache = wd.output_dir, wd.lod_cache_dir
    campus = read_campus(wd)
    frame = campus_frame(campus)
    if frame.crs is None:
        raise InputError(wd.campus_json, "the campus has no CRS: export needs one to georeference")
    if tiles is None:
        tiles = sorted(p.parent.name for p in recorded.glob(wd.root / "tiles", "*/merged.json"))
    if not tiles:
        raise InputError(wd.root / "tiles", "no merged tiles (tiles/*/merged.json): run the merge stage first")
    tree = plan_quadtree(list(tiles))
    georef = make_georef(frame.crs, frame.origin, _enu_centre(campus, frame.origin_array, tiles),
                         frame.vertical_datum, cfg.geoid_grid)
    base = content_hash(EXPORT_VERSION, cfg.model_dump(mode="json", exclude={"before"}), georef.to_json())
    state_path = out / "tileset.fingerprints.json"
    old = json.loads(state_path.read_text()).get("nodes", {}) if state_path.exists() else {}
    run = map_jobs if map_jobs is not None else partial(_run_jobs, workers=workers)
    nodes, built, reused = _build_tree(tree, wd.root / "tiles", NodeJob(tree.root, base, out, cache, georef, cfg),
                                       old, run)
    root = tree.root
    if root.key in built or not recorded.is_file(out / "overview.glb"):
        run([NodeJob(OVERVIEW, nodes[root.key]["fingerprint"], out, cache, georef, cfg,
                     children=(("root", {"key": root.key}),))])
    tileset = _write_tileset(out, tileset_json(tree, nodes, georef), georef, nodes)
    _remove_stale(out, cache, nodes)
    grades_mode = (campus.get("config") or {}).get("repair", {}).get("grades", "auto")  # what repair acted on
    points = write_points_overlay(wd.root / "tiles", out / "points", list(tiles), georef, grades_mode=grades_mode,
                                  run=map_jobs)  # beside the nodes: a cluster's workers read the stores
    before = (_export_before(wd, list(tiles), georef, cfg, base, run, grades_mode) if cfg.before
              else _drop_before(wd))
    leaves_built = [k for k in built if k.startswith("L0_")]
    return {
        "tiles": len(tiles), "nodes": len(nodes), "built": built, "reused": reused,
        "faces_in": int(sum(nodes[k]["faces"] for k in leaves_built)),
        "leaf_faces": int(sum(nodes[n.key]["faces"] for n in tree.levels[0])),
        "bytes": int(sum(rec["bytes"] for rec in nodes.values())), "compression": cfg.compression,
        "texture_bytes": int(sum(rec.get("texture_bytes", 0) for rec in nodes.values())),
        "root_geometric_error_m": nodes[root.key]["geometricError"], "seconds": time.perf_counter() - t0,
        "tileset": str(tileset), "overview": str(out / "overview.glb"), "georef": str(out / "georef.json"),
        "points": points, "before": before,
    }  # fmt: skip


# ------------------------------------------------------------------------------------- the input, for comparison

BEFORE = "before"  # output/before/: the input mesh as a tileset (export.before), export/before/: its tiles


def _drop_before(wd: WorkDir) -> None:
    for d in (wd.output_dir / BEFORE, wd.root / "export" / BEFORE, wd.lod_cache_dir / BEFORE):
        recorded.remove_tree(d)


def _export_before(wd: WorkDir, tiles: list[str], georef: GeoRef, cfg: ExportConfig, base: str,
                   run: Callable[[list[NodeJob]], list[dict]], grades_mode: str) -> dict:
    """``output/before/``: the input mesh of every tile (its store's faces, :func:`tasks.merge.input_tile_mesh`)
    as a tileset in the same frame, levels and format as the merged model's, for the viewer's before / after
    split. Each tile's input mesh is rebuilt only when its store changed. Returns {"tiles", "tileset"}."""
    from storage.contracts.tile_mesh import write_tile_mesh
    from storage.errors import EmptyTileError
    from storage.ids import TileId
    from tasks.merge import input_tile_mesh

    src = wd.root / "export" / BEFORE / "tiles"
    kept = []
    for key in tiles:
        tile_dir, dst = wd.root / "tiles" / key, src / key
        fp = store_fingerprint(tile_dir, sides=("grades",)) + grades_mode
        mark = dst / "input.fingerprint"
        if not (mark.exists() and mark.read_text() == fp and (dst / "merged.json").exists()):
            try:
                mesh = input_tile_mesh(TileId.from_key(key), tile_dir, grades_mode)
            except EmptyTileError:
                shutil.rmtree(dst, ignore_errors=True)
                continue
            write_tile_mesh(dst, mesh)
            mark.write_text(fp)
        kept.append(key)
    if not kept:
        _drop_before(wd)
        return {"tiles": 0, "tileset": None}
    tree = plan_quadtree(kept)
    out, cache = wd.output_dir / BEFORE, wd.lod_cache_dir / BEFORE
    state_path = out / "tileset.fingerprints.json"
    old = json.loads(state_path.read_text()).get("nodes", {}) if state_path.exists() else {}
    nodes, _, _ = _build_tree(tree, src, NodeJob(tree.root, content_hash(base, BEFORE), out, cache, georef, cfg),
                              old, run)
    tileset = _write_tileset(out, tileset_json(tree, nodes, georef), georef, nodes)
    _remove_stale(out, cache, nodes)
    return {"tiles": len(kept), "tileset": str(tileset)}


# ------------------------------------------------------------------------------------- in the flow


def run_export_stage(cfg, wd: WorkDir, map_jobs: Callable[[list[NodeJob]], list[dict]] | None = None) -> dict:
    """Export when any tile has a merged mesh, recorded as ("export", "tileset"); returns the unit summary
    (status done / empty / failed, ``error`` one line when failed).

    map_jobs: see :func:`run_export` (the flow maps the quadtree's nodes over its workers: each node is
    then recorded where it was built, see :func:`build_nodes`, and records of nodes no longer planned go)."""
    if not any((wd.root / "tiles").glob("*/merged.json")):
        return {"unit": "campus", "status": "empty", "skipped": False}
    built: list[str] = []

    def work() -> dict:
        out = run_export(wd.root, cfg.export, workers=1, map_jobs=map_jobs)  # no pool: a Dask worker may not fork
        built.extend(out["built"])
        if map_jobs is not None:
            from storage.workdir.housekeeping import drop_unplanned_records

            drop_unplanned_records(wd, "export", set(out["built"]) | set(out["reused"]) | {"tileset", OVERVIEW.key})
        return {**{k: v for k, v in out.items() if k not in ("built", "reused")}, "nodes_built": len(out["built"])}

    res = record_step(wd, "export", "tileset", work)
    if res["status"] == "failed":
        return {"unit": "campus", "skipped": False, **res}
    return {"unit": "tileset", "skipped": not built, **res}


def _node_cost(job) -> float:
    """A node's expected cost, to balance batches: a leaf's merged mesh bytes, a parent's children's faces
    (1 when unknown). Merged tiles differ a lot (92 to 2.4 M faces in the demo), so equal counts would not
    balance."""
    if not isinstance(job, NodeJob):
        return 1.0
    if job.tile_dir is not None:
        st = recorded.state(job.tile_dir / "merged.npz")  # on a bucket: the recorded size
        return float(st.size) if st is not None else 1.0
    return float(sum(rec.get("faces") or 0 for _, rec in job.children)) or 1.0


def node_batches(jobs: list[NodeJob], n_workers: int) -> list[list[tuple[int, NodeJob]]]:
    """The (index, job) batches the flow maps for one level of the quadtree: one node each up to 8 per
    worker (a leaf costs seconds, a task run ~0.3 s), else at most 8 per worker of about equal cost
    (:func:`_node_cost`), each in job order; the costliest first."""
    indexed = list(enumerate(jobs))
    return balanced_batches(indexed, [_node_cost(j) for j in jobs], 8 * n_workers)


def relocate_jobs(jobs: list[tuple[int, NodeJob]], old: Path, new: Path) -> list[tuple[int, NodeJob]]:
    """(index, job) pairs whose work-dir paths (``out``, ``cache``, ``tile_dir``) under ``old`` are moved under
    ``new``: jobs planned on one process's mirror of a work dir on a bucket, built on another's (``Path()`` for
    ``new`` or ``old``: paths relative to the work dir).

    >>> job = NodeJob(None, "fp", Path("/a/output"), Path("/a/export/lod"), None, None, Path("/a/tiles/1_2"))
    >>> moved = relocate_jobs([(0, job)], Path("/a"), Path())[0][1]
    >>> str(moved.out), str(moved.tile_dir), str(relocate_jobs([(0, moved)], Path(), Path("/b"))[0][1].cache)
    ('output', 'tiles/1_2', '/b/export/lod')
    """
    def move(p: Path | None) -> Path | None:
        return None if p is None else new / Path(p).relative_to(old)

    fields = ("out", "cache", "tile_dir")  # a PointsJob has no cache
    return [(i, replace(j, **{f: move(getattr(j, f)) for f in fields if hasattr(j, f)})) for i, j in jobs]


def _built(job: NodeJob) -> dict:
    rec = build_node(job)
    return {"uri": rec.get("uri"), "faces": rec.get("faces"), "record": rec}


def build_nodes(jobs: list[tuple[int, NodeJob]]) -> list[dict]:
    """Build a batch of nodes ((index, job) pairs, see :func:`node_batches`), each recorded in the manifest
    as ("export", node key) with its fingerprint, seconds and peak memory.

    Returns one dict per job: {"index", "status": "done", "record": the node's record} or
    {"index", "status": "failed", "error": "<node key>: <one line>"}."""
    out = []
    for i, job in jobs:
        if isinstance(job, PointsJob):  # a tile of the points overlay, mapped with the nodes
            try:
                out.append({"index": i, "status": "done", "record": build_points(job)})
            except (InputError, OSError) as e:
                out.append({"index": i, "status": "failed", "error": f"points {job.tile}: {failure_message(e)}"})
            continue
        res = record_step(WorkDir(job.out.parent), "export", job.node.key, partial(_built, job), job.fingerprint)
        if res["status"] == "failed":  # record_step prefixes the stage; the flow's message names the node
            out.append({"index": i, "status": "failed",
                        "error": f"{job.node.key}: {res['error'].removeprefix('export: ')}"})
        else:
            out.append({"index": i, "status": "done", "record": res["record"]})
    return out


def node_records(results: list[dict], n_jobs: int) -> list[dict]:
    """The node records in job order from the flattened results of mapped :func:`build_nodes` (entries
    without an index, e.g. a task that failed whole, are ignored). Raises InputError (one line) when a
    node failed or is missing.

    >>> node_records([{"index": 1, "status": "done", "record": "b"}, {"index": 0, "status": "done", "record": "a"}], 2)
    ['a', 'b']
    """
    got = {r["index"]: r for r in results if "index" in r}
    bad = [r.get("error", "export task failed") for r in got.values() if r["status"] != "done"]
    if bad or len(got) != n_jobs:
        raise InputError(None, "; ".join(bad) or "an export task failed (see the run history)")
    return [got[i]["record"] for i in range(n_jobs)]
