"""Quality of mesh files against a synth campus's truth (file-level wrapper of ``tasks.quality.metrics``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.meshes import read_mesh
from tasks.quality.metrics import evaluate_mesh, facade_mask
from tasks.quality.stats import QualityReport

CLASS_NAMES = ("ground", "road", "wall", "roof", "glass", "frame", "balcony", "eave")


def load_truth(synth_dir: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The truth mesh of a synth campus: (vertices (n,3) float64 world, faces (m,3), face_class (m,),
    frame_origin (3,)). Tiled campuses are concatenated."""
    d = Path(synth_dir) / "truth"
    plys = sorted(d.glob("truth_mesh*.ply"))
    if not plys:
        raise InputError(d, "no truth_mesh*.ply: not a synth campus folder")
    vs, fs, cs, off = [], [], [], 0
    for p in plys:
        m = read_mesh(p)
        cls = np.load(p.with_name(p.stem + "_faces.npz"))["face_class"]
        if len(cls) != m.n_faces:
            raise InputError(p, f"{m.n_faces} faces but {len(cls)} face classes (degenerate truth faces?)")
        vs.append(m.vertices)
        fs.append(m.faces + off)
        cs.append(cls)
        off += len(m.vertices)
    origin = np.asarray(json.loads((d / "registration.json").read_text())["frame_origin"], np.float64)
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(cs), origin


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
