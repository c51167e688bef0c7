"""The export stage: the merged tiles as georeferenced 3D Tiles 1.1 with levels of detail.

Reads ``campus.json`` (CRS, origin, grid) and every ``tiles/{ix}_{iy}/merged.npz`` + ``merged.json`` (the
merge stage's ``TileMesh``, with its textures). Writes ``output/tileset.json``, ``output/content/…`` (leaf
and LOD glbs), ``output/overview.glb``, ``output/georef.json``, ``output/tileset.fingerprints.json`` and
the per-node decimated meshes in ``export/lod/``; records ("export", "tileset") and, when the flow maps the
nodes, ("export", node key) in the manifest.

Invalidated per node: a leaf by its merged tile's content (mesh, metadata, textures), every node by the
export parameters, the georeference (CRS, origin, footprint centre) or ``EXPORT_VERSION``, a parent by
any child. Nodes, glbs and cached meshes the plan no longer names are removed.

Modules: ``tree`` (quadtree, tileset.json), ``content`` (a node's glTF content), ``nodes`` (one node's
build), ``gltf`` / ``vertex_split`` / ``lod`` / ``georef`` (glb writer, per-feature vertices, block-wise
decimation, ENU frame), ``check`` (validation:
``python -m tasks.export.check WORKDIR``), ``stage`` (the run and its records).
"""

from tasks.export.georef import EnuProjector, make_georef
from tasks.export.nodes import NodeJob, build_node
from tasks.export.stage import build_nodes, node_batches, node_records, run_export, run_export_stage

__all__ = ["EnuProjector", "NodeJob", "build_node", "build_nodes", "make_georef", "node_batches", "node_records",
           "run_export", "run_export_stage"]
