"""Building one node of the export quadtree from paths: a leaf from its merged tile, a parent from its
children's passed-up meshes, or the overview from the root's. Each writes its glb under the output
folder and its decimated mesh under the LOD cache; no work dir, no manifest (``stage.py`` records).

A node's fingerprint covers its inputs' content hashes, the parameters and the georeference, so a rerun
rebuilds a node only when it changed.
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from storage.atomic import write_parts_atomic
from storage.contracts.tile_mesh import read_tile_mesh, tile_mesh_content
from tasks.config import ExportConfig
from tasks.export.bake import BakeSource, bake_lod, pack_children
from tasks.export.content import bake_source, box_from_bounds, leaf_content, lod_gltf
from tasks.export.georef import EnuProjector, GeoRef
from tasks.export.gltf import GltfMesh, glb_parts
from tasks.export.lod import concat_lods, decimate, load_lod, save_lod, weld
from tasks.export.tree import QuadNode


def content_hash(*parts) -> str:
    """32 hex digits of sha256 over ``parts`` (bytes as they are, anything else as sorted JSON)."""
    h = hashlib.sha256()
    for p in parts:
        h.update(json.dumps(p, sort_keys=True, default=str).encode() if not isinstance(p, bytes) else p)
    return h.hexdigest()[:32]


def leaf_fingerprint(tile_dir: Path, base: str) -> str:
    """A leaf's fingerprint: ``base`` (version, parameters, georeference) and the merged tile's content
    (``merged.npz``, ``merged.json`` and its textures)."""
    return content_hash(base, *tile_mesh_content(tile_dir))


def _write_glb(out: Path, uri: str, mesh: GltfMesh, compression: str, texture: str = "jpeg",
               leaf: bool = False) -> int:
    """Stream the glb to a temporary name and rename it into place (never the whole glb in memory);
    "meshopt" geometry or "ktx2" textures (UASTC in leaves, ETC1S in parents): written plain, then
    compressed in place (:mod:`tasks.export.meshopt`). Returns its bytes."""
    ktx = texture == "ktx2" and bool(mesh.images)
    if compression != "meshopt" and not ktx:
        return write_parts_atomic(out / uri, glb_parts(mesh, compression))
    from tasks.export.meshopt import compress_glbs

    nbytes = write_parts_atomic(out / uri, glb_parts(mesh, "none"))  # ExportConfig refuses draco + ktx2
    return compress_glbs([out / uri], "meshopt" if compression == "meshopt" else "none",
                         ("uastc" if leaf else "etc1s") if ktx else "keep").get(str(out / uri), (0, nbytes))[1]


def _backend(cfg: ExportConfig) -> str | None:
    return None if cfg.decimator == "auto" else cfg.decimator


@dataclass(frozen=True)
class NodeJob:
    """What one node's build needs (picklable, for a process pool or a cluster)."""

    node: QuadNode  # h = -1: the overview
    fingerprint: str
    out: Path  # work_dir/output
    cache: Path  # work_dir/export/lod
    georef: GeoRef
    cfg: ExportConfig
    tile_dir: Path | None = None  # leaves
    children: tuple[tuple[str, dict], ...] = ()  # parents: (child key, child record); overview: ("root", {"key"})


def _build_leaf(job: NodeJob) -> dict:
    """Leaf: full-resolution content glb, and the decimated mesh it passes up (cached), with its atlas
    painted from the leaf's textures when ``lod_texture_px`` > 0 and the leaf has textures."""
    tm = read_tile_mesh(job.tile_dir)
    gltf, lod = leaf_content(tm, EnuProjector(job.georef), job.cfg)
    uri = f"content/tiles/{tm.tile}.glb"
    nbytes = _write_glb(job.out, uri, gltf, job.cfg.compression, job.cfg.texture, leaf=True)
    texture_bytes = sum(len(im.data) for im in gltf.images)
    tile, n_faces = tm.tile, tm.n_faces
    # a leaf without textures passes up vertex colours: an atlas would add nothing and lose the shading
    # (textured primitives are unlit)
    source = bake_source(gltf) if job.cfg.lod_texture_px and gltf.images else None
    del gltf, tm  # the decimation below needs only the LodMesh (and the bake its source)
    dec = decimate(lod, math.ceil(lod.n_faces / job.cfg.lod_reduction), job.cfg.hausdorff_samples, _backend(job.cfg))
    passed = bake_lod(dec.mesh, source, job.cfg.lod_texture_px) if source is not None else dec.mesh
    del source
    save_lod(job.cache / f"{job.node.key}.npz", passed)
    lo, hi = lod.bounds()
    return {"fingerprint": job.fingerprint, "uri": uri, "tile": tile, "lo": lo.tolist(), "hi": hi.tolist(),
            "box": box_from_bounds(lo, hi), "geometricError": 0.0, "up_hausdorff_m": dec.hausdorff_m,
            "faces": n_faces, "bytes": nbytes, "texture_bytes": texture_bytes}  # fmt: skip


def _build_parent(job: NodeJob) -> dict:
    """Parent: its children's passed-up meshes (content: their atlases packed 2 x 2 when any child is
    textured, else welded), and its own decimation passed up (its atlas painted from the content). So one
    untextured tile does not take the textures from every level above it; a campus without textures keeps
    lit vertex-coloured parents.
    geometricError = max over children of (child decimation's measured deviation + child's error)."""
    n, kids = job.node, dict(job.children)
    parts = [load_lod(job.cache / f"{k}.npz") for k in kids]
    textured = bool(job.cfg.lod_texture_px) and any(p.atlas is not None for p in parts)
    if textured:  # an untextured child beside textured ones: its vertex colours painted into an atlas of its own
        parts = [p if p.atlas is not None else bake_lod(p, BakeSource.of_lod(p), job.cfg.lod_texture_px)
                 for p in parts]
    content = pack_children(parts) if textured else weld(concat_lods(parts))
    del parts
    uri = f"content/lod{n.h}/{n.x}_{n.y}.glb"
    gltf = lod_gltf(content, job.cfg.jpeg_quality)
    texture_bytes = sum(len(im.data) for im in gltf.images)
    nbytes = _write_glb(job.out, uri, gltf, job.cfg.compression, job.cfg.texture)
    del gltf
    geometry = weld(content) if textured else content  # the decimation needs the seams closed
    dec = decimate(geometry, math.ceil(geometry.n_faces / job.cfg.lod_reduction), job.cfg.hausdorff_samples, _backend(job.cfg))
    passed = bake_lod(dec.mesh, BakeSource.of_lod(content), job.cfg.lod_texture_px) if textured else dec.mesh
    save_lod(job.cache / f"{n.key}.npz", passed)
    lo, hi = content.bounds()
    lo = np.minimum(lo, np.min([r["lo"] for r in kids.values()], axis=0))
    hi = np.maximum(hi, np.max([r["hi"] for r in kids.values()], axis=0))
    error = max(r["up_hausdorff_m"] + r["geometricError"] for r in kids.values())
    return {"fingerprint": job.fingerprint, "uri": uri, "lo": lo.tolist(), "hi": hi.tolist(),
            "box": box_from_bounds(lo, hi), "geometricError": float(error), "up_hausdorff_m": dec.hausdorff_m,
            "faces": content.n_faces, "bytes": nbytes, "texture_bytes": texture_bytes}  # fmt: skip


def release_freed_memory() -> None:
    """Give the heap's free pages back to the OS (glibc ``malloc_trim``; a no-op elsewhere).

    A node frees its arrays when it ends, but glibc keeps freed heap pages mapped, so a worker's RSS would
    stay at its largest node's peak and count against every later unit it runs (measured: 1.28 GB left
    after a 2.4 M-face leaf). No ``gc.collect()``: the arrays go by reference counting, and a full collection
    in a busy worker costs a quarter of a second or more per call."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def build_node(job: NodeJob) -> dict:
    """Build one node of the export quadtree (a leaf from its merged tile, a parent from its children's
    cached meshes, or the overview); picklable, so a flow can map it over workers. Freed memory goes back
    to the OS before and after, so a node's peak is its own working set."""
    release_freed_memory()
    try:
        if job.node.h < 0:
            return _build_overview(job)
        return _build_leaf(job) if job.node.h == 0 else _build_parent(job)
    finally:
        release_freed_memory()


def _build_overview(job: NodeJob) -> dict:
    root = load_lod(job.cache / f"{dict(job.children)['root']['key']}.npz")
    textured = root.atlas is not None
    geometry = weld(root) if textured else root
    ov = decimate(geometry, job.cfg.overview_max_faces, job.cfg.hausdorff_samples, _backend(job.cfg)).mesh
    if textured:  # the root's own atlas when nothing was decimated, else one painted from it (twice its side)
        ov = root if ov is geometry else bake_lod(ov, BakeSource.of_lod(root), 2 * job.cfg.lod_texture_px)
    nbytes = _write_glb(job.out, "overview.glb", lod_gltf(ov, job.cfg.jpeg_quality), job.cfg.compression,
                        job.cfg.texture)
    return {"fingerprint": job.fingerprint, "uri": "overview.glb", "bytes": nbytes}

