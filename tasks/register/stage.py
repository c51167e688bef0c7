"""The register stage: the similarity that maps the MLS clouds onto the mesh, once per campus.

``registration.mode``:

- ``auto``: register (SAC-IA + Scale-ICP, :mod:`tasks.register.align`) when the inputs or the parameters
  changed since the recorded transform; otherwise reuse it. The estimate is applied only when it beats
  the transform in place (the recorded one, else the identity) on held-out points, within the scale
  prior (:mod:`tasks.register.guard`); otherwise that transform stays, and one warning line says why
  (also when the fit fails and a transform is recorded: the run goes on with it). ``registration.strict``
  turns a flagged registration into an error.
- ``pinned``: reuse the recorded transform (``registration.json`` of the work dir, or
  ``registration.matrix`` of the config) whatever the inputs do, so a changed or added input redoes
  only its own tiles. This is the mode for scheduled reprocessing once a campus is registered.
- ``off``: the inputs are already co-registered; identity, after a check that measures the MLS
  points' distance to the mesh surface where they overlap (a warning, not an error, when it fails).

Both sides are bounded samples, whatever the campus size: MLS points from short ranges spread over
each file (``registration.max_points``), and the mesh's area-weighted surface samples written by the
scan stage.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from ms3d_model.hashing import order_free_subset
from storage.atomic import write_json_atomic
from storage.contracts.surface_samples import read_surface_samples, samples_path
from storage.errors import InputError
from storage.formats.copc import copc_level_counts, is_copc, iter_copc
from storage.formats.points import iter_points, iter_points_range
from storage.frame import CampusFrame
from storage.inputs.identity import InputFile
from storage.inputs.remote import is_url, local_input, redact, split_url
from storage.workdir.layout import WorkDir
from storage.workdir.manifest import combine_fingerprints
from tasks.config import CampusConfig
from tasks.scan import outside_box, points_box
from tasks.units import Done, run_unit

log = logging.getLogger("ms3d.register")

REGISTRATION_FILE = "registration.json"


def _copc_sample(path: Path, n_target: int, box, cfg: CampusConfig) -> list[np.ndarray]:
    """World points of a COPC file in ``box`` ((2, 2) world metres) from its coarsest octree levels that hold
    about ``n_target`` points over the box: a thinned cloud, the finer nodes left compressed."""
    s = cfg.inputs.units_scale
    query = np.asarray(box, np.float64) / s
    level = int(np.searchsorted(np.cumsum(copc_level_counts(path, query)), n_target))
    out = [ch.xyz[np.all((ch.xyz[:, :2] * s >= box[0]) & (ch.xyz[:, :2] * s <= box[1]), axis=1)] * s
           for ch in iter_copc(path, cfg.tiling.chunk_points, query, max_level=level)]
    n = sum(len(x) for x in out)
    return [x[:: max(n // max(n_target, 1), 1)] for x in out]


def sample_points_for_registration(rec: InputFile, n_target: int, cfg: CampusConfig, n_ranges: int = 16,
                                   box=None) -> np.ndarray:
    """About n_target world points spread over a cloud file: ``n_ranges`` short ranges (LAS/LAZ) or a
    strided pass (other formats); with a points ``box`` ([xmin, ymin, xmax, ymax], ``inputs.points_bounds``)
    only points inside it, a COPC file's from its coarse octree levels over the box. A file that breaks
    part-way ends its sample early (logged)."""
    bounds = None if box is None else [list(box[:2]), list(box[2:])]
    if bounds is None and is_url(rec.path) and Path(split_url(rec.path)[1]).suffix.lower() in (".las", ".laz") \
            and rec.count > n_target:  # its ranges by range GETs: the header, the chunk table, a few chunks
        return _remote_ranges(rec, n_target, cfg, n_ranges)
    path = Path(local_input(rec.path))  # any other input by URL is read from a staged copy
    out = []
    try:
        if bounds is not None and is_copc(path):
            out = _copc_sample(path, n_target, bounds, cfg)
        elif path.suffix.lower() in (".las", ".laz") and rec.count > n_target:
            per, starts = _range_starts(rec.count, n_target, n_ranges)
            for a in starts:
                for ch in iter_points_range(path, int(a), int(a) + per, per, cfg.inputs.units_scale, bounds):
                    out.append(ch.xyz)
        else:
            stride = max(rec.count // max(n_target, 1), 1)
            for ch in iter_points(path, cfg.tiling.chunk_points, cfg.inputs.units_scale, bounds):
                out.append(ch.xyz[::stride])
    except InputError as e:
        log.info("registration sample of %s ended early: %s", path, e)  # the file fails its own units
    xyz = np.concatenate(out) if out else np.zeros((0, 3))
    return xyz[np.isfinite(xyz).all(axis=1)]


def _range_starts(count: int, n_target: int, n_ranges: int) -> tuple[int, np.ndarray]:
    """(points per range, (n_ranges,) int64 first point of each): ranges spread evenly over ``count``."""
    per = max(n_target // n_ranges, 1)
    return per, np.linspace(0, max(count - per, 0), n_ranges).astype(np.int64)


def _remote_ranges(rec: InputFile, n_target: int, cfg: CampusConfig, n_ranges: int) -> np.ndarray:
    """:func:`sample_points_for_registration` of a LAS/LAZ object by URL, read by ranged GETs
    (:func:`storage.patches.ranges.open_ranged`): the same ranges, hence the same points, as from a staged copy."""
    from storage.formats.las import iter_las_object
    from storage.inputs.remote import bucket_store
    from storage.patches.ranges import open_ranged

    per, starts = _range_starts(rec.count, n_target, n_ranges)
    out = []
    try:
        with open_ranged(*bucket_store(rec.path), buffer_size=1 << 18) as f:  # 256 KiB per ranged GET
            for a in starts:
                for ch in iter_las_object(f, redact(rec.path), per, int(a), int(a) + per):
                    out.append(ch.xyz * cfg.inputs.units_scale if cfg.inputs.units_scale != 1.0 else ch.xyz)
    except InputError as e:
        log.info("registration sample of %s ended early: %s", redact(rec.path), e)
    xyz = np.concatenate(out) if out else np.zeros((0, 3))
    return xyz[np.isfinite(xyz).all(axis=1)]


def mesh_target(records: list[InputFile], wd: WorkDir, frame: CampusFrame) -> tuple[np.ndarray, np.ndarray]:
    """The scan stage's surface samples of every readable mesh: ((k, 3) float64 campus-local, (k, 3) normals)."""
    xyz, nrm = [], []
    for r in records:
        if r.kind == "mesh" and not r.error:
            p = samples_path(wd, r.source)
            if p.exists():
                x, n = read_surface_samples(p, frame.origin_array)
                xyz.append(x)
                nrm.append(n)
    if not xyz:
        raise InputError(None, "no readable mesh to register to: " + "; ".join(r.error for r in records if r.error))
    return np.concatenate(xyz), np.concatenate(nrm)


def mls_sample(records: list[InputFile], cfg: CampusConfig, frame: CampusFrame) -> np.ndarray:
    """A bounded sample of every readable point cloud (in ``inputs.points_bounds``), (n, 3) float64 campus-local."""
    box = points_box(records, cfg.inputs.points_bounds, cfg.grid())
    pts = [r for r in records if r.kind == "points" and not r.error and not outside_box(r, box)]
    n_each = max(cfg.registration.max_points * 4 // max(len(pts), 1), 10_000)
    parts = [sample_points_for_registration(r, n_each, cfg, box=box) for r in pts]
    src = np.concatenate(parts) - frame.origin_array if parts else np.zeros((0, 3))
    if len(src) < 100:
        raise InputError(None, "no readable MLS points to register: " + "; ".join(r.error for r in records if r.error))
    return src


def _recorded(wd: WorkDir) -> dict | None:
    p = wd.root / REGISTRATION_FILE
    try:
        return json.loads(p.read_text())
    except (FileNotFoundError, json.JSONDecodeError):
        return None


def _estimate(records: list[InputFile], frame: CampusFrame, cfg: CampusConfig, wd: WorkDir) -> dict:
    from tasks.register.align import check_coregistered_samples
    from tasks.register.guard import guarded_register

    src = mls_sample(records, cfg, frame)
    tgt, nrm = mesh_target(records, wd, frame)
    # rows in an order of their coordinates, not of the files' source ids (hashes of their paths): every seeded
    # subsample after this picks the same points when the same inputs come under other names or URLs
    seed = int(cfg.registration.seed)
    src = src[order_free_subset(src, len(src), seed)]
    order = order_free_subset(tgt, len(tgt), seed)
    tgt, nrm = tgt[order], nrm[order]
    if cfg.registration.mode == "off":
        check = check_coregistered_samples(src, tgt, nrm, seed=cfg.registration.seed)
        if not check.ok:
            log.warning("registration is off but %s: the inputs do not look co-registered "
                        "(set registration.mode: auto)", check)
        return {"matrix": np.eye(4).tolist(), "scale": 1.0, "method": "identity (registration off)",
                "check": check.to_json()}
    recorded = _recorded(wd)
    if recorded is not None and recorded.get("frame_origin", frame.to_json().get("origin")) != frame.to_json().get("origin"):
        recorded = None  # recorded in another campus frame: not comparable
    reg = guarded_register(src, tgt, nrm, cfg.registration, recorded) | {"frame_origin": frame.to_json().get("origin")}
    if reg["warning"]:
        log.info("%s", reg["warning"])  # the run summary prints it: one line, not two
    return reg


def run_register(records: list[InputFile], frame: CampusFrame, cfg: CampusConfig, wd: WorkDir) -> dict:
    """The campus registration as a dict (``matrix`` 4x4 MLS world-minus-origin -> campus-local, ``scale``,
    ``method``, figures). Raises InputError when it cannot be had (pinned with nothing recorded, no
    readable inputs)."""
    mode = cfg.registration.mode
    if mode == "pinned":
        if cfg.registration.matrix is not None:
            m = np.asarray(cfg.registration.matrix, np.float64)
            if m.shape != (4, 4) or not np.isfinite(m).all():
                raise InputError(None, "registration.matrix must be a finite 4x4 matrix")
            return {"matrix": m.tolist(), "scale": float(np.cbrt(abs(np.linalg.det(m[:3, :3])))),
                    "method": "pinned (config)"}
        rec = _recorded(wd)
        if rec is None:
            raise InputError(wd.root / REGISTRATION_FILE, "registration.mode is pinned but no transform is recorded: "
                                                          "run once with mode auto, or give registration.matrix")
        return rec | {"method": f"pinned ({rec.get('method', 'recorded')})"}
    box = points_box(records, cfg.inputs.points_bounds, cfg.grid())  # the MLS sampled: a new box re-registers
    fp = combine_fingerprints(sorted(f"{r.kind}:{r.source}:{r.fingerprint}:{r.error != ''}" for r in records)
                              + [json.dumps(frame.to_json(), sort_keys=True)] + ([json.dumps(box)] if box else []))

    def work() -> Done:
        reg = _estimate(records, frame, cfg, wd)
        write_json_atomic(wd.root / REGISTRATION_FILE, reg)
        return Done(outputs=[REGISTRATION_FILE], summary={k: reg.get(k) for k in (
            "scale", "fitness", "method", "displacement_p50_m", "displacement_max_m", "warning")})

    res = run_unit(wd, "register", "campus", fp, cfg.stage_params("register"), work)
    if res["status"] == "failed":
        raise InputError(None, res["error"])
    reg = _recorded(wd)
    if reg is None:
        raise InputError(wd.root / REGISTRATION_FILE, "the recorded registration is missing or unreadable")
    return reg | {"seconds": res.get("seconds", 0.0), "reused": bool(res.get("skipped"))}
