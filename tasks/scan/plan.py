"""What the scan stage reads, and how its files are batched into task runs.

Pure-ish: reads the input folders' listings and file sizes, never the files' contents.
"""

from __future__ import annotations

from pathlib import Path

from storage.errors import InputError
from storage.formats.camera_files import read_cameras
from storage.inputs.identity import Discovery, InputFile, assign_source_ids, discover
from storage.inputs.remote import input_is_file, local_input
from tasks.batches import balanced_batches
from tasks.config import CampusConfig
from tasks.scan.placement import check_productions

MESH_READ_WEIGHT = 20.0  # a mesh is read whole and sampled: ~20x the cost of a cloud header per byte


def scan_files(cfg: CampusConfig) -> tuple[Discovery, dict[str, int], list[dict]]:
    """Discover the inputs of ``cfg``: (discovery, {path: stable source id}, one {"path", "kind", "source"}
    per file, meshes first). Raises InputError when the configured labels file is missing, and for a
    ContextCapture production whose metadata is bad, missing or disagrees with the config
    (:func:`tasks.scan.placement.check_productions`)."""
    found = discover(cfg.inputs.mesh, cfg.inputs.points)
    check_productions(found.meshes, cfg)
    if cfg.inputs.labels and not input_is_file(cfg.inputs.labels):
        raise InputError(cfg.inputs.labels, "labels file not found (inputs.labels in the config)")
    if cfg.inputs.cameras:  # a broken camera file stops the run before any work, not in the last stage
        read_cameras(local_input(cfg.inputs.cameras))
    ids = assign_source_ids(list(found.meshes) + list(found.points))
    files = [{"path": p, "kind": "mesh", "source": ids[p]} for p in found.meshes] + \
            [{"path": p, "kind": "points", "source": ids[p]} for p in found.points]
    return found, ids, files


def file_size(path: str) -> float:
    """Size of a file in bytes plus one (1.0 when it cannot be read): a batching weight."""
    try:
        return float(Path(path).stat().st_size) + 1.0
    except OSError:
        return 1.0


def scan_batches(files: list[dict], n_workers: int) -> list[list[dict]]:
    """Files of :func:`scan_files` in at most ``4 * n_workers`` batches of about equal cost (meshes are
    read whole: weighted :data:`MESH_READ_WEIGHT` x their size; clouds only by their size)."""
    weights = [file_size(f["path"]) * (MESH_READ_WEIGHT if f["kind"] == "mesh" else 1) for f in files]
    return balanced_batches(files, weights, 4 * max(n_workers, 1))


def scanned_records(batches: list[list[dict]], scans: list[dict]) -> list[InputFile]:
    """The :class:`InputFile` record of each scanned file (batches flattened, in order), from the scan
    summaries ``scans`` (one per file); a file whose scan returned no record gets its error."""
    records = []
    for f, s in zip([f for b in batches for f in b], scans):
        rec = s.get("record") or InputFile(f["source"], f["path"], f["kind"], "",
                                           error=s.get("error", "scan failed")).to_json()
        records.append(InputFile(**rec))
    return records
