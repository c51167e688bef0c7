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
    content/{level}/{x}/{y}.glb   export.tiling implicit: the same glbs, moved (``implicit.py``), and
    subtrees/{level}/{x}/{y}.subtree  their availability; tileset.json then has one implicit root
    tileset.3tz                   export.archive 3tz: the above as one 3D Tiles archive (state in
                                  work_dir/export/archive.json)
    (work_dir/export/lod/*.npz    per node: the decimated mesh it passes to its parent)

Every face carries grade / source / region as EXT_mesh_features + EXT_structural_metadata.

Memory is bounded by a tile: a leaf is converted alone; a parent reads its children's passed-up meshes
(each decimated by ``lod_reduction``), welds them, and passes up its own decimation. A rerun rebuilds a
node only when its fingerprint (its inputs' content hashes, the parameters and the georeference)
changed: one changed tile rewrites that tile's content and its ancestors, nothing else.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import file_sha256, write_bytes_atomic, write_json_atomic
from storage.errors import InputError
from storage.formats.threetz import write_3tz
from storage.patches.state import store_fingerprint
from storage.workdir.layout import WorkDir, campus_frame, read_campus
from tasks.config import ExportConfig
from tasks.export.batching import node_batches, node_records, relocate_jobs  # noqa: F401 - the package exports them from here
from tasks.export.georef import EnuProjector, GeoRef, make_georef
from tasks.export.implicit import implicit_files, implicit_uris
from tasks.export.nodes import NodeJob, build_node, content_hash, leaf_fingerprint
from tasks.export.overlay import PointsJob, build_points, write_points_overlay
from tasks.export.tree import EXPORT_VERSION, QuadNode, QuadTree, plan_quadtree, tileset_json
from tasks.units import failure_message, record_step

OVERVIEW = QuadNode(-1, 0, 0)
NOT_CONTENT = {"before", "tiling", "subtree_levels", "archive"}  # export fields no node's content depends on

# ------------------------------------------------------------------------------------- the export run


def _tile_grid(campus: dict, origin: np.ndarray) -> tuple[np.ndarray, float]:
    """(the south-west corner of ground tile 0_0 (2,) campus-local metres, the tile side in metres)."""
    if "grid" in campus:  # a pipeline work dir: tile keys are world-anchored (storage.grid), not origin-relative
        grid = campus["grid"]
        return np.asarray(grid["anchor_m"][:2], np.float64) - origin[:2], float(grid["tile_size_m"])
    return np.zeros(2), float(campus.get("config", {}).get("tiling", {}).get("tile_size_m", 100.0))


def _enu_centre(campus: dict, origin: np.ndarray, tiles: list[str]) -> tuple[float, float, float]:
    """Centre of the tiles' footprint (campus-local metres, z 0): the origin of the ENU frame."""
    ij = np.array([[int(v) for v in k.split("_")] for k in tiles], np.float64)
    corner, size = _tile_grid(campus, origin)
    centre = (ij.min(axis=0) + ij.max(axis=0) + 1) / 2 * size + corner
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


def _write_tileset(out: Path, doc: dict, georef: GeoRef, nodes: dict[str, dict], overview: str | None = None) -> Path:
    """tileset.json (rewritten only when its bytes change), georef.json and tileset.fingerprints.json (with
    the fingerprint of the root the overview was built from)."""
    text = (json.dumps(doc, indent=1) + "\n").encode()
    tileset = out / "tileset.json"
    if not tileset.exists() or tileset.read_bytes() != text:
        write_bytes_atomic(tileset, text)
    write_json_atomic(out / "georef.json", georef.to_json())
    state = {"version": EXPORT_VERSION, "nodes": nodes} | ({"overview": overview} if overview else {})
    write_json_atomic(out / "tileset.fingerprints.json", state)
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


# ------------------------------------------------------------------------------------- tiling and archive

ARCHIVED = ("tileset.json", "georef.json", "overview.glb", "content", "subtrees", "points", "before")
NOT_ARCHIVED = ("tileset.fingerprints.json", "fingerprints.json")  # rerun state, not read by a viewer


def _place_content(out: Path, nodes: dict[str, dict], uris: dict[str, str] | None) -> dict[str, dict]:
    """The records with each node's glb moved (never copied) to ``uris[key]`` (implicit tiling), or back to
    where its build wrote it (``uris`` None); ``built_uri`` keeps the build's path while moved, so a rerun
    reuses the node either way. Through temporary names: a tree whose height changed swaps implicit paths."""
    moves, placed = [], {}
    for key, rec in nodes.items():
        built = rec.get("built_uri", rec["uri"])
        want = uris[key] if uris is not None else built
        if rec["uri"] != want:
            moves.append((out / rec["uri"], out / "content" / f".moving-{key}.glb", out / want))
        placed[key] = {k: v for k, v in rec.items() if k != "built_uri"} | {"uri": want}
        if want != built:
            placed[key]["built_uri"] = built
    for src, tmp, _ in moves:
        recorded.ensure_local(src)
        os.replace(src, tmp)
    for _, tmp, dst in moves:
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, dst)
    return placed


def _tileset_doc(out: Path, tree: QuadTree, nodes: dict[str, dict], georef: GeoRef, cfg: ExportConfig,
                 grid: tuple[np.ndarray, float]) -> tuple[dict, dict[str, dict]]:
    """(the tileset document, the node records) for ``cfg.tiling``: explicit, or implicit (the glbs moved to
    the implicit paths, ``subtrees/`` written, :mod:`tasks.export.implicit`); subtrees no longer planned go.
    grid: :func:`_tile_grid`, whose squares the implicit root box subdivides."""
    implicit = cfg.tiling == "implicit"
    nodes = _place_content(out, nodes, implicit_uris(tree) if implicit else None)
    doc, subtrees = tileset_json(tree, nodes, georef), {}
    if implicit:
        doc, subtrees = implicit_files(tree, nodes, georef, *grid, EnuProjector(georef).local_to_enu,
                                       cfg.subtree_levels)
    for rel, data in subtrees.items():
        if not ((out / rel).is_file() and (out / rel).read_bytes() == data):
            write_bytes_atomic(out / rel, data)
    for stale in recorded.glob(out / "subtrees", "**/*.subtree"):
        if stale.relative_to(out).as_posix() not in subtrees:
            recorded.unlink(stale)
    for folder in sorted((*out.glob("content/**/"), *out.glob("subtrees/**/")), reverse=True):
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    return doc, nodes


def _write_archive(wd: WorkDir, kind: str) -> dict | None:
    """``output/tileset.3tz`` (``kind`` "3tz"): the files of :data:`ARCHIVED`, tileset.json first, rewritten
    only when one changed (paths, sizes, a small file's sha256 or a large one's mtime, kept in
    ``export/archive.json``). "none": no archive (None)."""
    out, dest, state = wd.output_dir, wd.tileset_3tz, wd.root / "export" / "archive.json"
    if kind == "none":
        recorded.unlink(dest)
        recorded.unlink(state)
        return None
    files = []
    for name in ARCHIVED:
        found = [out / name] if recorded.is_file(out / name) else recorded.glob(out / name, "**/*")
        files += [f for f in found if recorded.is_file(f) and f.name not in NOT_ARCHIVED and f.name[0] != "."]
    rels = [f.relative_to(out).as_posix() for f in files]
    sizes = [recorded.state(f).size for f in files]
    key = content_hash([(r, n, file_sha256(f) if n <= 1 << 20 else recorded.state(f).mtime_ns)
                        for r, n, f in zip(rels, sizes, files)])
    old = json.loads(state.read_text()) if state.is_file() else {}
    have = recorded.state(dest)
    if old.get("key") == key and have is not None and have.size == old.get("bytes"):
        return {"path": str(dest), "entries": len(files), "bytes": have.size, "written": False}
    recorded.ensure_local(*files)
    summary = write_3tz(dest, list(zip(rels, files)))
    write_json_atomic(state, {"key": key, "bytes": summary["bytes"]})
    return {"path": str(dest), **summary, "written": True}


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
    base = content_hash(EXPORT_VERSION, cfg.model_dump(mode="json", exclude=NOT_CONTENT), georef.to_json())
    state_path = out / "tileset.fingerprints.json"
    old_state = json.loads(state_path.read_text()) if state_path.exists() else {}
    old = old_state.get("nodes", {})
    run = map_jobs if map_jobs is not None else partial(_run_jobs, workers=workers)
    nodes, built, reused = _build_tree(tree, wd.root / "tiles", NodeJob(tree.root, base, out, cache, georef, cfg),
                                       old, run)
    root = tree.root
    overview = nodes[root.key]["fingerprint"]  # a new root may be a reused node: the overview follows the root
    if root.key in built or old_state.get("overview") != overview or not recorded.is_file(out / "overview.glb"):
        run([NodeJob(OVERVIEW, overview, out, cache, georef, cfg, children=(("root", {"key": root.key}),))])
    doc, nodes = _tileset_doc(out, tree, nodes, georef, cfg, _tile_grid(campus, frame.origin_array))
    tileset = _write_tileset(out, doc, georef, nodes, overview)
    _remove_stale(out, cache, nodes)
    grades_mode = (campus.get("config") or {}).get("repair", {}).get("grades", "auto")  # what repair acted on
    points = write_points_overlay(wd.root / "tiles", out / "points", list(tiles), georef, grades_mode=grades_mode,
                                  run=map_jobs)  # beside the nodes: a cluster's workers read the stores
    before = (_export_before(wd, list(tiles), georef, cfg, base, run, grades_mode,
                             _tile_grid(campus, frame.origin_array)) if cfg.before else _drop_before(wd))
    leaves_built = [k for k in built if k.startswith("L0_")]
    return {
        "tiles": len(tiles), "nodes": len(nodes), "built": built, "reused": reused,
        "faces_in": int(sum(nodes[k]["faces"] for k in leaves_built)),
        "leaf_faces": int(sum(nodes[n.key]["faces"] for n in tree.levels[0])),
        "bytes": int(sum(rec["bytes"] for rec in nodes.values())), "compression": cfg.compression,
        "texture_bytes": int(sum(rec.get("texture_bytes", 0) for rec in nodes.values())),
        "root_geometric_error_m": nodes[root.key]["geometricError"], "seconds": time.perf_counter() - t0,
        "tileset": str(tileset), "overview": str(out / "overview.glb"), "georef": str(out / "georef.json"),
        "points": points, "before": before, "tiling": cfg.tiling, "archive": _write_archive(wd, cfg.archive),
    }  # fmt: skip


# ------------------------------------------------------------------------------------- the input, for comparison

BEFORE = "before"  # output/before/: the input mesh as a tileset (export.before), export/before/: its tiles


def _drop_before(wd: WorkDir) -> None:
    for d in (wd.output_dir / BEFORE, wd.root / "export" / BEFORE, wd.lod_cache_dir / BEFORE):
        recorded.remove_tree(d)


def _export_before(wd: WorkDir, tiles: list[str], georef: GeoRef, cfg: ExportConfig, base: str,
                   run: Callable[[list[NodeJob]], list[dict]], grades_mode: str, grid: tuple[np.ndarray, float]
                   ) -> dict:
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
    doc, nodes = _tileset_doc(out, tree, nodes, georef, cfg, grid)
    tileset = _write_tileset(out, doc, georef, nodes)
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
