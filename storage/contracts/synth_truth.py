"""The ground truth of a synth campus, as ``synth`` writes it and the quality stage reads it::

    truth/truth_mesh*.ply          the true surface (one per tile of a tiled campus), world coordinates
    truth/truth_mesh*_faces.npz    its per-face class (``face_class``, one per face of the .ply)
    truth/registration.json        the mesh frame's ``frame_origin`` (and the MLS perturbation)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.meshes import read_mesh


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


__all__ = ["load_truth"]
