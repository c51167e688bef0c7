"""The register stage: the similarity that maps the MLS clouds onto the mesh, once per campus
(Liu et al. 2023, §3.1: SAC-IA then Scale-ICP; modes auto / pinned / off, see :mod:`tasks.register.stage`).

- Reads: the scan records of the inputs, a bounded sample of every readable point cloud, and the mesh
  surface samples the scan stage wrote (``scan/{source:08x}.npz``).
- Writes: ``registration.json`` (4x4 matrix MLS world-minus-origin -> campus-local, scale, method,
  figures) and one manifest record (unit ``campus``).
- Invalidated by (mode ``auto``): any input's kind, source id, content fingerprint or error state, the
  campus frame, the registration parameters and ``STAGE_VERSIONS["register"]``. ``pinned`` never
  re-estimates; ``off`` is the identity after a co-registration check.

The pure algorithm is in :mod:`tasks.register.align` (coarse, fine, target, check and base modules).
"""

from tasks.stages import StageSpec, lazy_exports

# it reads the scan's surface samples and its own record, never the tiles, stores or regions of earlier runs
STAGE = StageSpec("register", "campus", reads=("manifest.d/register/", "scan/", "registration.json"))

# the names below load on first use (tasks.stages.lazy_exports): importing the package for its STAGE costs
# nothing, and a worker loads only the modules its tasks run
__getattr__ = lazy_exports(__name__, {
    "tasks.register.stage": "run_register",
    "tasks.register.target": "mesh_registration_target",
})

__all__ = ["STAGE", "mesh_registration_target", "run_register"]
