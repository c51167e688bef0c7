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

from tasks.scan.frame import campus_frame
from tasks.scan.placement import MeshPlacement, mesh_placement
from tasks.scan.plan import file_size, scan_batches, scan_files, scanned_records
from tasks.scan.stage import run_scan_file

__all__ = ["MeshPlacement", "campus_frame", "file_size", "mesh_placement", "run_scan_file", "scan_batches", "scan_files",
           "scanned_records"]
