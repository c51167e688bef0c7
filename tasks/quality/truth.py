"""Quality of mesh files against a synth campus's truth (file-level wrapper of ``tasks.quality.metrics``;
the truth read by :func:`storage.contracts.synth_truth.load_truth`)."""

from __future__ import annotations

from pathlib import Path

from storage.contracts.synth_truth import load_truth
from storage.formats.meshes import read_mesh
from tasks.quality.metrics import evaluate_mesh, facade_mask
from tasks.quality.stats import QualityReport

__all__ = ["CLASS_NAMES", "load_truth", "quality_of_campus", "quality_of_mesh"]

CLASS_NAMES = ("ground", "road", "wall", "roof", "glass", "frame", "balcony", "eave")


def quality_of_mesh(pred_path: str | Path, synth_dir: str | Path, offset=None, spacing_m: float = 0.05,
                    **kwargs) -> QualityReport:
    """Accuracy/completeness/F-score/hole area of the mesh at ``pred_path`` (file or folder of tiles)
    against the synth truth; ``offset`` (world) is added to the mesh's coordinates (default: the
    synth frame origin, as for the synth MVS mesh). Evaluated in the local frame around the origin."""
    tv, tf, tc, origin = load_truth(synth_dir)
    pred = read_mesh(pred_path, offset=origin if offset is None else offset)
    return evaluate_mesh(pred.vertices - origin, pred.faces, tv - origin, tf, spacing_m=spacing_m,
                         true_face_mask=facade_mask(tc), true_face_class=tc, class_names=CLASS_NAMES, **kwargs)


def quality_of_campus(synth_dir: str | Path, spacing_m: float = 0.05) -> QualityReport:
    """The baseline: the synth campus's own MVS mesh (``mesh/``) against its truth."""
    return quality_of_mesh(Path(synth_dir) / "mesh", synth_dir, spacing_m=spacing_m)
