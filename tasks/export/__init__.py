"""The export stage: the merged tiles as georeferenced 3D Tiles 1.1 with levels of detail.

Reads ``campus.json`` (CRS, origin, grid) and every ``tiles/{ix}_{iy}/merged.npz`` + ``merged.json`` (the
merge stage's ``TileMesh``, with its textures). Writes ``output/tileset.json``, ``output/content/…`` (leaf
and LOD glbs; with ``export.tiling: implicit`` at ``content/{level}/{x}/{y}.glb``, and ``output/subtrees/``),
``output/overview.glb``, ``output/georef.json``, ``output/tileset.fingerprints.json``, with ``export.archive:
3tz`` ``output/tileset.3tz`` (its state in ``export/archive.json``), and the per-node decimated meshes in
``export/lod/``; records ("export", "tileset") and, when the flow maps the
nodes, ("export", node key) in the manifest.

Invalidated per node: a leaf by its merged tile's content (mesh, metadata, textures), every node by the
export parameters (not the layout: tiling and archive move and pack the same glbs), the georeference (CRS, origin, footprint centre) or ``EXPORT_VERSION``, a parent by
any child. Nodes, glbs and cached meshes the plan no longer names are removed.

Modules: ``tree`` (quadtree, tileset.json), ``implicit`` (the same quadtree as implicit tiling: subtrees,
export.tiling), ``content`` (a node's glTF content), ``nodes`` (one node's build), ``gltf`` / ``vertex_split``
/ ``lod`` / ``georef`` (glb writer, per-feature vertices, block-wise decimation, ENU frame), ``overlay`` (the
points overlay's tiles), ``check`` (validation: ``python -m tasks.export.check WORKDIR``), ``batching`` (the
flow's node batches), ``stage`` (the run, the layout and the .3tz archive (export.archive), its records).
"""

from tasks.stages import BatchContext, StageSpec, lazy_exports


def node_task_batches(jobs: list, ctx: BatchContext) -> list[list]:
    """The export's batching rule: :func:`tasks.export.stage.node_batches` for ``ctx.n_workers``."""
    from tasks.export.stage import node_batches  # on first use: the package stays light (lazy_exports)

    return node_batches(jobs, ctx.n_workers)

STAGE = StageSpec("export-nodes", "node", node_task_batches, reads=(), duration="5s", priority=10)
"""The quadtree's levels are the chain the run waits on: a queued node must not wait behind the side tasks. On a
bucket a node task pulls only the records: it downloads its merged tile or its children's LOD meshes where it
reads them (:mod:`storage.recorded`)."""

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.export.georef": "EnuProjector make_georef",
    "tasks.export.nodes": "NodeJob build_node",
    "tasks.export.stage": "build_nodes node_batches node_records node_task_batches relocate_jobs run_export run_export_stage",
})

__all__ = ["STAGE", "EnuProjector", "NodeJob", "build_node", "build_nodes", "make_georef", "node_batches", "node_records",
           "relocate_jobs", "run_export", "run_export_stage"]
