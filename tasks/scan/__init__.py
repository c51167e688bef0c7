"""The scan stage: each input file read once per content, then the campus frame chosen.

- Reads: the configured mesh and point-cloud files (meshes whole, clouds only their headers).
- Writes: one manifest record per file (unit ``{source:08x}``) carrying the file's
  :class:`storage.inputs.identity.InputFile` record (bounds, count, CRS, error), and for each readable mesh its
  surface samples ``scan/{source:08x}.npz`` (``storage.contracts.surface_samples``), which registration aligns to.
- Invalidated by: the file's content fingerprint (for a tile of a ContextCapture production, with its
  ``metadata.xml``: :mod:`tasks.scan.placement`), its path and kind, the scan parameters
  (``registration.target_spacing_m``, units, mesh offset) and ``STAGE_VERSIONS["scan"]``.

A file that cannot be read is still scanned: its record carries the error and, where the file says so,
its bounds (:mod:`tasks.scan.salvage`), so that exactly the tiles it covers are blocked.
"""

from tasks.stages import BatchContext, StageSpec, lazy_exports


def scan_task_batches(files: list[dict], ctx: BatchContext) -> list[list[dict]]:
    """The scan stage's batching rule: :func:`tasks.scan.plan.scan_batches` for ``ctx.n_workers``."""
    from tasks.scan.plan import scan_batches  # on first use (lazy_exports)

    return scan_batches(files, ctx.n_workers)

STAGE = StageSpec("scan", "file", scan_task_batches, reads=("manifest.d/scan/", "scan/"))

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.scan.extent": "Box clip_point_records files_outside_box outside_box points_box",
    "tasks.scan.frame": "campus_frame",
    "tasks.scan.placement": "MeshPlacement mesh_placement place_mesh",
    "tasks.scan.plan": "file_size scan_batches scan_files scan_task_batches scanned_records",
    "tasks.scan.stage": "run_scan_file",
})

__all__ = ["STAGE", "Box", "MeshPlacement", "campus_frame", "clip_point_records", "file_size", "files_outside_box", "mesh_placement", "outside_box", "place_mesh",
           "points_box", "run_scan_file", "scan_batches", "scan_files",
           "scanned_records"]
