"""Ground-truth labels of patches: -1 unknown, 0 good, 1 bad.

Two sources:

- a synth ``defects.json``: ``{"frame_origin": [x, y, z], "defects": [{"samples": [[x, y, z], ...],
  "faces": [f, ...], ...}, ...]}``. Samples are points on each defect in the synth mesh frame (world =
  sample + frame_origin). A patch is bad when any defect sample falls in it; every other patch present
  is good.
- a CSV of patch ids ``i,j,k[,label]`` (an optional header line ``i,j,k[,label]``; label defaults to
  1 = bad, 0 = good). Listed-good and unlisted patches are both good.

Patch keys here are the store's ``patch`` column (:class:`storage.grid.PatchGrid`): the grid is
anchored in world coordinates, so a CSV of ``i,j,k`` stays valid whatever the campus extent.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.grid import PatchGrid


def _load_json(path: Path) -> dict:
    try:
        doc = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, "defects file not found") from None
    except (OSError, UnicodeDecodeError, ValueError) as exc:
        raise InputError(path, f"not valid JSON ({exc})") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("defects"), list):
        raise InputError(path, "expected an object with a 'defects' list")
    return doc


def load_defect_samples(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Defect sample points of a synth defects.json, in world coordinates.

    Returns:
        xyz_world: (n, 3) float64 metres (samples + frame_origin).
        defect_id: (n,) int64 index of each sample's defect in the file's ``defects`` list.
    """
    path = Path(path)
    doc = _load_json(path)
    try:
        origin = np.asarray(doc["frame_origin"], dtype=np.float64).reshape(3)
    except (KeyError, TypeError, ValueError):
        raise InputError(path, "'frame_origin' must be a list of 3 numbers (world position of the synth frame)") \
            from None
    chunks, ids = [], []
    for d, defect in enumerate(doc["defects"]):
        samples = defect.get("samples", []) if isinstance(defect, dict) else None
        try:
            s = np.asarray(samples, dtype=np.float64).reshape(-1, 3)
        except (TypeError, ValueError):
            raise InputError(path, f"defect {d}: 'samples' must be a list of [x, y, z]") from None
        if not np.isfinite(s).all():
            raise InputError(path, f"defect {d}: samples contain NaN or infinity")
        chunks.append(s)
        ids.append(np.full(len(s), d, dtype=np.int64))
    xyz = np.concatenate(chunks) if chunks else np.zeros((0, 3))
    return xyz + origin, (np.concatenate(ids) if ids else np.zeros(0, dtype=np.int64))


def load_defect_faces(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Face indices (in the synth mesh) of each defect: ((f,) int64 face index, (f,) int64 defect index)."""
    path = Path(path)
    doc = _load_json(path)
    faces, ids = [], []
    for d, defect in enumerate(doc["defects"]):
        try:
            f = np.asarray(defect.get("faces", []) if isinstance(defect, dict) else None, dtype=np.int64).reshape(-1)
        except (TypeError, ValueError):
            raise InputError(path, f"defect {d}: 'faces' must be a list of integer face indices") from None
        faces.append(f)
        ids.append(np.full(len(f), d, dtype=np.int64))
    return (np.concatenate(faces) if faces else np.zeros(0, np.int64),
            np.concatenate(ids) if ids else np.zeros(0, np.int64))


def bad_keys_from_defects(path: str | Path, grid: PatchGrid) -> np.ndarray:
    """Patches touched by any defect sample: (b,) int64 packed keys of ``grid``, sorted unique.

    path: synth defects.json (samples in world coordinates once its ``frame_origin`` is added).
    """
    world, _ = load_defect_samples(path)
    try:
        return np.unique(grid.pack(grid.cells_world(world)))
    except ValueError as exc:
        raise InputError(path, f"defect samples do not lie near the campus ({exc}): wrong frame_origin?") from None


def bad_keys_from_faces(defect_faces: np.ndarray, src_face: np.ndarray, face_patch: np.ndarray) -> np.ndarray:
    """Patches holding any defect face (for labels by mesh face rather than by sample point).

    defect_faces: (f,) int64 face indices in the source mesh; src_face, face_patch: (m,) int64 columns of a
    faces table. Returns (b,) int64 sorted unique keys.
    """
    hit = np.isin(np.asarray(src_face), np.asarray(defect_faces))
    return np.unique(np.asarray(face_patch)[hit])


def read_labels_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Rows of a patch label CSV ``i,j,k[,label]``: ((r,) int64 packed keys, (r,) int8 labels)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError(path, "labels CSV not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(path, f"cannot read ({exc})") from None
    rows = [(n, r) for n, r in enumerate(csv.reader(text.splitlines()), start=1)
            if r and any(c.strip() for c in r) and not r[0].lstrip().startswith("#")]
    if rows and [c.strip().lower() for c in rows[0][1]] in (["i", "j", "k"], ["i", "j", "k", "label"]):
        rows = rows[1:]
    ijk = np.zeros((len(rows), 3), dtype=np.int64)
    labels = np.ones(len(rows), dtype=np.int8)
    for r, (line, cells) in enumerate(rows):  # a hand-made file of a few thousand lines at most
        if len(cells) not in (3, 4):
            raise InputError(path, f"line {line}: expected i,j,k[,label], got {len(cells)} columns")
        try:
            values = [int(c.strip()) for c in cells]
        except ValueError:
            raise InputError(path, f"line {line}: non-integer value in {','.join(cells)!r}") from None
        ijk[r] = values[:3]
        if len(values) == 4:
            if values[3] not in (0, 1):
                raise InputError(path, f"line {line}: label must be 0 (good) or 1 (bad), got {values[3]}")
            labels[r] = values[3]
    try:
        keys = PatchGrid.pack(ijk)
    except ValueError as exc:
        raise InputError(path, str(exc)) from None
    return keys, labels


def bad_keys_from_csv(path: str | Path) -> np.ndarray:
    """(b,) int64 sorted unique keys of the patches a label CSV marks bad (label 1 or no label)."""
    keys, labels = read_labels_csv(path)
    return np.unique(keys[labels == 1])


def labels_for_patches(patch_keys: np.ndarray, bad_keys: np.ndarray) -> np.ndarray:
    """(u,) int64 patch keys -> (u,) int8 labels: 1 where the key is in ``bad_keys``, else 0."""
    return np.isin(np.asarray(patch_keys, dtype=np.int64), np.asarray(bad_keys, dtype=np.int64)).astype(np.int8)
