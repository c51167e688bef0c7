"""Export: the merged ground tiles as georeferenced 3D Tiles 1.1 (tileset.json + glb) with levels of detail.

Output (``work_dir/output``)::

    tileset.json                  3D Tiles 1.1: a quadtree over the ground tiles, refine REPLACE, root
                                  ``transform`` = float64 ENU->ECEF (column-major)
    content/tiles/{ix}_{iy}.glb   leaves: full resolution, textured + vertex-coloured primitives
    content/lod{h}/{x}_{y}.glb    parents h levels above the leaves: decimated, vertex-coloured
    overview.glb                  the whole campus decimated, same ENU frame (y-up glTF)
    georef.json                   source CRS, origin, vertical datum, ENU origin, the PROJ operation and
                                  what was assumed
    tileset.fingerprints.json     per node: input fingerprint, box, geometric error (for reruns)
    (work_dir/export/lod/*.npz    per node: the decimated mesh it passes to its parent)

Every face carries grade / source / region as EXT_mesh_features + EXT_structural_metadata.

Memory is bounded by a tile: a leaf is converted alone; a parent reads its children's passed-up meshes
(each decimated by ``lod_reduction``), welds them, and passes up its own decimation. A rerun rebuilds a
node only when its fingerprint (its inputs' content hashes, the parameters and the georeference)
changed: one changed tile rewrites that tile's content and its ancestors, nothing else.
"""

from __future__ import annotations

import hashlib
import io
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import file_fingerprint, file_sha256, write_bytes_atomic, write_json_atomic
from storage.errors import InputError
from storage.tile_mesh import TileMesh, read_tile_mesh, tile_mesh_paths

from tasks.config import ExportConfig
from tasks.export.georef import EnuProjector, GeoRef, enu_to_gltf, make_georef
from tasks.export.gltf import GltfImage, GltfMesh, build_glb, split_by_feature
from tasks.export.lod import LodMesh, concat_lods, decimate, load_lod, sample_colors, save_lod, weld

EXPORT_VERSION = 1
MIN_HALF_EXTENT_M = 0.01
BOX_PAD_M = 0.001  # bounding boxes grow by this, so lossy (Draco-quantized) positions stay inside

# ------------------------------------------------------------------------------------- quadtree


@dataclass(frozen=True, order=True)
class QuadNode:
    """Node (h, x, y) of the export quadtree: ``h`` levels above the leaves; it covers ground tiles
    ``ix0 + x * 2**h <= ix < ix0 + (x + 1) * 2**h`` (same for y), (ix0, iy0) the minimum tile."""

    h: int
    x: int
    y: int

    @property
    def key(self) -> str:
        return f"L{self.h}_{self.x}_{self.y}"

    @property
    def parent(self) -> QuadNode:
        return QuadNode(self.h + 1, self.x // 2, self.y // 2)


@dataclass(frozen=True)
class QuadTree:
    """levels[h]: the nodes of level h (sorted); children[node]: its children; leaf_tile[node]: "ix_iy"."""

    levels: list[list[QuadNode]]
    children: dict[QuadNode, list[QuadNode]]
    leaf_tile: dict[QuadNode, str]

    @property
    def root(self) -> QuadNode:
        return self.levels[-1][0]


def plan_quadtree(tile_keys: list[str]) -> QuadTree:
    """The quadtree over ground tiles ``tile_keys`` ("ix_iy"), anchored at the minimum tile.

    >>> t = plan_quadtree(["0_0", "1_0", "2_1"])
    >>> [[n.key for n in level] for level in t.levels]
    [['L0_0_0', 'L0_1_0', 'L0_2_1'], ['L1_0_0', 'L1_1_0'], ['L2_0_0']]
    """
    if not tile_keys:
        raise ValueError("no tiles to export")
    ij = np.array([[int(v) for v in k.split("_")] for k in tile_keys])
    lo = ij.min(axis=0)
    span = int((ij.max(axis=0) - lo).max()) + 1
    height = max(0, math.ceil(math.log2(span)))
    leaves = {QuadNode(0, int(i - lo[0]), int(j - lo[1])): k for (i, j), k in zip(ij, tile_keys)}
    levels = [sorted(leaves)]
    children: dict[QuadNode, list[QuadNode]] = {}
    for _ in range(height):
        parents: dict[QuadNode, list[QuadNode]] = {}
        for n in levels[-1]:
            parents.setdefault(n.parent, []).append(n)
        children.update(parents)
        levels.append(sorted(parents))
    return QuadTree(levels, children, leaves)


# ------------------------------------------------------------------------------------- pure content


def feature_rows(grade: np.ndarray, source: np.ndarray, region: np.ndarray):
    """One feature per distinct (grade, source, region): (feature per face (m,), grade (k,) int8,
    source (k,) int8, region (k,) int32), features ordered by (region, grade, source).

    >>> f, g, s, r = feature_rows(np.array([0, 1, 0], np.int8), np.array([0, 1, 0], np.int8), np.array([-1, 4, -1]))
    >>> f.tolist(), g.tolist(), s.tolist(), r.tolist()
    ([0, 1, 0], [0, 1], [0, 1], [-1, 4])
    """
    if len(grade) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int8), np.zeros(0, np.int8), np.zeros(0, np.int32)
    key = ((np.asarray(region, np.int64) + 1) << 8) | ((np.asarray(grade, np.int64) + 1) << 2) | np.asarray(source, np.int64)
    rows, inverse = np.unique(key, return_inverse=True)
    return (inverse.reshape(-1), (((rows >> 2) & 0x3F) - 1).astype(np.int8), (rows & 0x3).astype(np.int8),
            ((rows >> 8) - 1).astype(np.int32))


def box_from_bounds(lo, hi) -> list[float]:
    """3D Tiles ``box`` (centre, three half-axes) of the axis-aligned box [lo, hi] (ENU metres), grown by
    ``BOX_PAD_M``."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    c = (lo + hi) / 2
    h = np.maximum((hi - lo) / 2 + BOX_PAD_M, MIN_HALF_EXTENT_M)
    return [*map(float, c), float(h[0]), 0.0, 0.0, 0.0, float(h[1]), 0.0, 0.0, 0.0, float(h[2])]


def prepare_texture(path: str, uv: np.ndarray, max_px: int, quality: int) -> tuple[GltfImage, np.ndarray, np.ndarray]:
    """Crop an atlas to the pixels ``uv`` (k, 2) (glTF convention) use, downscale to ``max_px``.

    Returns (encoded image, its pixels (H, W, 3) uint8, uv remapped to the new image (k, 2) float32).
    The file's own bytes are embedded when neither crop nor downscale is needed.
    """
    from PIL import Image

    with Image.open(path) as im:
        fmt, (w0, h0) = im.format, im.size
        x0 = max(0, math.floor(float(uv[:, 0].min()) * w0) - 2) if len(uv) else 0
        x1 = min(w0, math.ceil(float(uv[:, 0].max()) * w0) + 2) if len(uv) else w0
        y0 = max(0, math.floor(float(uv[:, 1].min()) * h0) - 2) if len(uv) else 0
        y1 = min(h0, math.ceil(float(uv[:, 1].max()) * h0) + 2) if len(uv) else h0
        cw, ch = max(1, x1 - x0), max(1, y1 - y0)
        scale = min(1.0, max_px / max(cw, ch))
        whole = (x0, y0, x1, y1) == (0, 0, w0, h0)
        if fmt == "JPEG" and scale < 1.0:
            im.draft("RGB", (math.ceil(w0 * scale), math.ceil(h0 * scale)))  # decode at 1/2, 1/4.. directly
        f = im.size[0] / w0
        rgb = im.convert("RGB")
        if not whole:
            rgb = rgb.crop((math.floor(x0 * f), math.floor(y0 * f), math.ceil(x1 * f), math.ceil(y1 * f)))
        size = (max(1, round(cw * scale)), max(1, round(ch * scale)))
        if rgb.size != size:
            rgb = rgb.resize(size, Image.BILINEAR)
        if whole and scale == 1.0 and fmt in ("JPEG", "PNG"):
            data, mime = Path(path).read_bytes(), "image/jpeg" if fmt == "JPEG" else "image/png"
        else:
            buf = io.BytesIO()
            if fmt == "PNG":
                rgb.save(buf, format="PNG", compress_level=3)
                mime = "image/png"
            else:
                rgb.save(buf, format="JPEG", quality=quality)
                mime = "image/jpeg"
            data = buf.getvalue()
        pixels = np.asarray(rgb)
    new_uv = np.empty_like(uv, dtype=np.float32)
    new_uv[:, 0] = (uv[:, 0] * w0 - x0) / cw
    new_uv[:, 1] = (uv[:, 1] * h0 - y0) / ch
    return GltfImage(data, mime), pixels, new_uv


def leaf_content(tm: TileMesh, projector: EnuProjector, cfg: ExportConfig) -> tuple[GltfMesh, LodMesh]:
    """A ground tile's full-resolution content (glTF, y-up) and its vertex-coloured LodMesh (ENU)."""
    # one vertex per (vertex, texture) so each texture's crop can remap its own uvs
    faces, src, group = split_by_feature(tm.faces, tm.face_texture.astype(np.int64) + 1)
    group -= 1
    enu = projector.local_to_enu(tm.vertices)[src]
    uv = np.zeros((len(src), 2), np.float32)
    colors = (tm.vertex_colors[src] if tm.vertex_colors is not None else np.full((len(src), 3), 180, np.uint8)).copy()
    images = []
    used_textures = sorted(int(g) for g in np.unique(group) if g >= 0)
    face_texture = np.full(len(faces), -1, np.int16)
    for new_index, k in enumerate(used_textures):
        sel = group == k
        uv_gltf = np.stack([tm.uv[src[sel], 0], 1.0 - tm.uv[src[sel], 1]], axis=1)
        image, pixels, uv[sel] = prepare_texture(tm.textures[k], uv_gltf, cfg.max_texture_px, cfg.jpeg_quality)
        colors[sel] = sample_colors(pixels, uv[sel])
        images.append(image)
        face_texture[tm.face_texture == k] = new_index
    feature, g_rows, s_rows, r_rows = feature_rows(tm.grade, tm.source, tm.region)
    gltf = GltfMesh(positions=enu_to_gltf(enu), faces=faces, feature=feature, grade=g_rows, source=s_rows,
                    region=r_rows, face_texture=face_texture, uv=uv if images else None, vertex_colors=colors,
                    images=images)  # fmt: skip
    lod = weld(LodMesh(enu.astype(np.float32), faces.astype(np.int32), colors, tm.grade, tm.source, tm.region))
    return gltf, lod


def lod_gltf(lod: LodMesh) -> GltfMesh:
    """A LodMesh as vertex-coloured glTF content (y-up)."""
    feature, g_rows, s_rows, r_rows = feature_rows(lod.grade, lod.source, lod.region)
    return GltfMesh(positions=enu_to_gltf(lod.positions), faces=lod.faces, feature=feature, grade=g_rows,
                    source=s_rows, region=r_rows, face_texture=np.full(lod.n_faces, -1, np.int16),
                    vertex_colors=lod.colors)  # fmt: skip


def tileset_json(tree: QuadTree, nodes: dict[str, dict], georef: GeoRef) -> dict:
    """The 3D Tiles 1.1 document. nodes[key]: {"uri", "box", "geometricError"} per quadtree node."""

    def tile(n: QuadNode) -> dict:
        rec = nodes[n.key]
        t = {"boundingVolume": {"box": rec["box"]}, "geometricError": rec["geometricError"], "refine": "REPLACE",
             "content": {"uri": rec["uri"]}}
        kids = tree.children.get(n, [])
        if kids:
            t["children"] = [tile(c) for c in kids]
        return t

    root = tile(tree.root)
    root = {"transform": georef.tileset_transform(), **root}
    half = np.asarray(root["boundingVolume"]["box"][3:], float).reshape(3, 3)
    diagonal = float(2 * np.linalg.norm(half.sum(axis=0)))
    return {
        "asset": {"version": "1.1", "generator": f"ms3d export v{EXPORT_VERSION}"},
        "geometricError": max(diagonal, root["geometricError"]),
        "root": root,
    }


# ------------------------------------------------------------------------------------- stage


def _sha(*parts) -> str:
    h = hashlib.sha256()
    for p in parts:
        h.update(json.dumps(p, sort_keys=True, default=str).encode() if not isinstance(p, bytes) else p)
    return h.hexdigest()[:32]


def _leaf_fingerprint(tile_dir: Path, base: str) -> str:
    npz, meta = tile_mesh_paths(tile_dir)
    doc = json.loads(meta.read_text())
    textures = [file_fingerprint((tile_dir / t).resolve()) for t in doc["textures"]]
    return _sha(base, file_sha256(npz), meta.read_bytes(), textures)


def _write_glb(out: Path, uri: str, mesh: GltfMesh, compression: str) -> int:
    data = build_glb(mesh, compression)
    write_bytes_atomic(out / uri, data)
    return len(data)


def _backend(cfg: ExportConfig) -> str | None:
    return None if cfg.decimator == "auto" else cfg.decimator


def _tile_size_m(campus: dict) -> float:
    return float(campus.get("config", {}).get("tiling", {}).get("tile_size_m", 100.0))


@dataclass(frozen=True)
class _Job:
    """What one node's build needs (picklable, for a process pool)."""

    node: QuadNode
    fingerprint: str
    out: Path
    cache: Path
    georef: GeoRef
    cfg: ExportConfig
    tile_dir: Path | None = None  # leaves
    children: tuple[tuple[str, dict], ...] = ()  # parents: (child key, child record)


def _build_leaf(job: _Job) -> dict:
    """Leaf: full-resolution content glb, and the decimated mesh it passes up (cached)."""
    tm = read_tile_mesh(job.tile_dir)
    gltf, lod = leaf_content(tm, EnuProjector(job.georef), job.cfg)
    uri = f"content/tiles/{tm.tile}.glb"
    nbytes = _write_glb(job.out, uri, gltf, job.cfg.compression)
    texture_bytes = sum(len(im.data) for im in gltf.images)
    del gltf
    dec = decimate(lod, math.ceil(lod.n_faces / job.cfg.lod_reduction), job.cfg.hausdorff_samples, _backend(job.cfg))
    save_lod(job.cache / f"{job.node.key}.npz", dec.mesh)
    lo, hi = lod.bounds()
    return {"fingerprint": job.fingerprint, "uri": uri, "tile": tm.tile, "lo": lo.tolist(), "hi": hi.tolist(),
            "box": box_from_bounds(lo, hi), "geometricError": 0.0, "up_hausdorff_m": dec.hausdorff_m,
            "faces": tm.n_faces, "bytes": nbytes, "texture_bytes": texture_bytes}  # fmt: skip


def _build_parent(job: _Job) -> dict:
    """Parent: its children's passed-up meshes welded (content), and its own decimation passed up.
    geometricError = max over children of (child decimation's measured deviation + child's error)."""
    n, kids = job.node, dict(job.children)
    content = weld(concat_lods([load_lod(job.cache / f"{k}.npz") for k in kids]))
    uri = f"content/lod{n.h}/{n.x}_{n.y}.glb"
    nbytes = _write_glb(job.out, uri, lod_gltf(content), job.cfg.compression)
    dec = decimate(content, math.ceil(content.n_faces / job.cfg.lod_reduction), job.cfg.hausdorff_samples, _backend(job.cfg))
    save_lod(job.cache / f"{n.key}.npz", dec.mesh)
    lo, hi = content.bounds()
    lo = np.minimum(lo, np.min([r["lo"] for r in kids.values()], axis=0))
    hi = np.maximum(hi, np.max([r["hi"] for r in kids.values()], axis=0))
    error = max(r["up_hausdorff_m"] + r["geometricError"] for r in kids.values())
    return {"fingerprint": job.fingerprint, "uri": uri, "lo": lo.tolist(), "hi": hi.tolist(),
            "box": box_from_bounds(lo, hi), "geometricError": float(error), "up_hausdorff_m": dec.hausdorff_m,
            "faces": content.n_faces, "bytes": nbytes, "texture_bytes": 0}  # fmt: skip


def _run_jobs(fn, jobs: list[_Job], workers: int) -> list[dict]:
    if workers <= 1 or len(jobs) <= 1:
        return [fn(j) for j in jobs]
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    ctx = multiprocessing.get_context("forkserver")
    with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx) as pool:
        return list(pool.map(fn, jobs))


def build_node(job: _Job) -> dict:
    """Build one node of the export quadtree (a leaf from its merged tile, a parent from its children's
    cached meshes, or the overview); picklable, so a flow can map it over workers."""
    if job.node.h < 0:
        return _build_overview(job)
    return _build_leaf(job) if job.node.h == 0 else _build_parent(job)


def _build_overview(job: _Job) -> dict:
    root_key = dict(job.children)["root"]["key"]
    ov = decimate(load_lod(job.cache / f"{root_key}.npz"), job.cfg.overview_max_faces, job.cfg.hausdorff_samples,
                  _backend(job.cfg)).mesh
    nbytes = _write_glb(job.out, "overview.glb", lod_gltf(ov), job.cfg.compression)
    return {"fingerprint": job.fingerprint, "uri": "overview.glb", "bytes": nbytes}


def run_export(work_dir: str | Path, config: ExportConfig | None = None, tiles: list[str] | None = None,
               workers: int = 1, map_jobs=None) -> dict:
    """Write ``work_dir/output`` (see the module docstring) from ``tiles/*/merged.npz``.

    tiles: tile keys to export (default: every tile with a merged mesh). workers: processes building
    the nodes of one level side by side (1 inside a Dask worker, whose daemon process may not fork a
    pool; memory grows to ``workers`` tiles). map_jobs: instead, a callable ``(jobs) -> records`` that
    runs :func:`build_node` on every job (in order), e.g. as tasks mapped over a cluster; this function
    then only plans, and writes the small JSON files. Returns a summary: nodes built / reused, faces,
    bytes, seconds, the paths written.
    """
    from storage.workdir import WorkDir, campus_frame, read_campus

    t0 = time.perf_counter()
    cfg = config or ExportConfig()
    wd = WorkDir(work_dir)
    out, cache = wd.root / "output", wd.root / "export" / "lod"
    campus = read_campus(wd)
    frame = campus_frame(campus)
    if frame.crs is None:
        raise InputError(wd.campus_json, "the campus has no CRS: export needs one to georeference")
    if tiles is None:
        tiles = sorted(p.parent.name for p in (wd.root / "tiles").glob("*/merged.json"))
    if not tiles:
        raise InputError(wd.root / "tiles", "no merged tiles (tiles/*/merged.json): run the merge stage first")
    tree = plan_quadtree(list(tiles))

    size = _tile_size_m(campus)
    ij = np.array([[int(v) for v in k.split("_")] for k in tiles], np.float64)
    centre = ((ij.min(axis=0) + ij.max(axis=0) + 1) / 2) * size
    if "grid" in campus:  # a pipeline work dir: tile keys are world-anchored (storage.grid), not origin-relative
        grid = campus["grid"]
        centre = ((ij.min(axis=0) + ij.max(axis=0) + 1) / 2) * float(grid["tile_size_m"]) \
            + np.asarray(grid["anchor_m"][:2], np.float64) - frame.origin_array[:2]
    georef = make_georef(frame.crs, frame.origin, (centre[0], centre[1], 0.0), frame.vertical_datum)
    base = _sha(EXPORT_VERSION, cfg.model_dump(mode="json"), georef.to_json())

    state_path = out / "tileset.fingerprints.json"
    old = json.loads(state_path.read_text()).get("nodes", {}) if state_path.exists() else {}
    nodes: dict[str, dict] = {}
    built, reused = [], []

    def fresh(key: str, fp: str) -> bool:
        rec = old.get(key)
        return bool(rec) and rec["fingerprint"] == fp and (out / rec["uri"]).exists() and (cache / f"{key}.npz").exists()

    for level in tree.levels:
        jobs = []
        for n in level:
            if n.h == 0:
                tile_dir = wd.root / "tiles" / tree.leaf_tile[n]
                job = _Job(n, _leaf_fingerprint(tile_dir, base), out, cache, georef, cfg, tile_dir=tile_dir)
            else:
                kids = tuple((c.key, nodes[c.key]) for c in tree.children[n])
                job = _Job(n, _sha(base, [r["fingerprint"] for _, r in kids]), out, cache, georef, cfg, children=kids)
            if fresh(n.key, job.fingerprint):
                nodes[n.key] = old[n.key]
                reused.append(n.key)
            else:
                jobs.append(job)
        results = (map_jobs(jobs) if map_jobs is not None else _run_jobs(build_node, jobs, workers)) if jobs else []
        for job, rec in zip(jobs, results):
            nodes[job.node.key] = rec
            built.append(job.node.key)

    root = tree.root
    overview = out / "overview.glb"
    if root.key in built or not overview.exists():
        job = _Job(QuadNode(-1, 0, 0), nodes[root.key]["fingerprint"], out, cache, georef, cfg,
                   children=(("root", {"key": root.key}),))
        (map_jobs([job]) if map_jobs is not None else [build_node(job)])

    doc = tileset_json(tree, nodes, georef)
    text = (json.dumps(doc, indent=1) + "\n").encode()
    tileset = out / "tileset.json"
    if not tileset.exists() or tileset.read_bytes() != text:
        write_bytes_atomic(tileset, text)
    write_json_atomic(out / "georef.json", georef.to_json())
    write_json_atomic(state_path, {"version": EXPORT_VERSION, "nodes": nodes})

    named = {rec["uri"] for rec in nodes.values()}
    for stale in (out / "content").rglob("*.glb"):
        if stale.relative_to(out).as_posix() not in named:
            stale.unlink()
    for stale in cache.glob("*.npz"):
        if stale.stem not in nodes:
            stale.unlink()
    leaves_built = [k for k in built if k.startswith("L0_")]
    return {
        "tiles": len(tiles), "nodes": len(nodes), "built": built, "reused": reused,
        "faces_in": int(sum(nodes[k]["faces"] for k in leaves_built)),
        "leaf_faces": int(sum(nodes[n.key]["faces"] for n in tree.levels[0])),
        "bytes": int(sum(rec["bytes"] for rec in nodes.values())), "compression": cfg.compression,
        "texture_bytes": int(sum(rec.get("texture_bytes", 0) for rec in nodes.values())),
        "root_geometric_error_m": nodes[root.key]["geometricError"], "seconds": time.perf_counter() - t0,
        "tileset": str(tileset), "overview": str(overview), "georef": str(out / "georef.json"),
    }  # fmt: skip
