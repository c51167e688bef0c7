"""The per-face quality of a leaf's glb: a second ``EXT_mesh_features`` feature id set (``_FEATURE_ID_1``, one
feature per face) indexing a second ``EXT_structural_metadata`` property table, ``face_quality``:

- ``deviation_m`` (FLOAT32, metres): the signed scan-to-model distance of the MLS points nearest to the face,
  positive where the scan lies in front of the face (the model behind it), NaN where no point is near
  (:mod:`tasks.geometry.deviation`);
- ``confidence`` (FLOAT32): the grader's p(bad) of the patch the face came from, NaN where it was not graded.

A feature per face means a vertex per face corner: only leaves (full resolution, uncompressed) carry it; LOD
parents and Draco leaves do not, and a viewer shows them as having no value. Pure.

    >>> faces, src, fid1 = split_per_face(np.array([[0, 1, 2], [2, 1, 3]]), np.array([4, 7]))
    >>> faces.tolist(), src.tolist(), fid1.tolist()
    ([[0, 1, 2], [3, 4, 5]], [0, 1, 2, 2, 1, 3], [4, 4, 4, 7, 7, 7])
"""

from __future__ import annotations

import numpy as np

FACE_QUALITY_CLASS = {
    "name": "Face quality",
    "properties": {
        "deviation_m": {"type": "SCALAR", "componentType": "FLOAT32", "required": True,
                        "description": "signed scan-to-model distance (metres) of the MLS points nearest to the face: "
                                       "positive where the scan lies in front of the face, NaN where no point is near"},
        "confidence": {"type": "SCALAR", "componentType": "FLOAT32", "required": True,
                       "description": "the grader's p(bad) of the patch the face came from, NaN where it was not graded"},
    },
}  # fmt: skip
MAX_FACES_USHORT = 65535  # feature ids of a primitive above this are FLOAT (exact below 2**24)


def split_per_face(faces: np.ndarray, face_index: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Three vertices of its own per face. faces: (m, 3) int; face_index: (m,) int64 the faces' rows in the
    property table. Returns (new faces (m, 3) int64, source vertex per new vertex (3m,) int64, feature id
    per new vertex (3m,) int64)."""
    m = len(faces)
    return (np.arange(3 * m, dtype=np.int64).reshape(m, 3), np.asarray(faces, np.int64).reshape(-1),
            np.repeat(np.asarray(face_index, np.int64), 3))


def face_quality_table(view, deviation: np.ndarray, confidence: np.ndarray) -> dict:
    """The ``face_quality`` property table; ``view(bytes) -> bufferView index`` appends its columns."""
    return {"class": "face_quality", "count": int(len(deviation)), "name": "face_quality", "properties": {
        "deviation_m": {"values": view(np.asarray(deviation, np.float32).tobytes())},
        "confidence": {"values": view(np.asarray(confidence, np.float32).tobytes())}}}


def feature_id_values(fid: np.ndarray) -> tuple[np.ndarray, int]:
    """A feature id attribute's values and component type: (n, 2) uint16 padded to 4 bytes (UNSIGNED_SHORT,
    5123) while ids fit, else (n,) float32 (FLOAT, 5126; glTF forbids UNSIGNED_INT vertex attributes)."""
    if len(fid) == 0 or int(fid.max()) < MAX_FACES_USHORT:
        padded = np.zeros((len(fid), 2), np.uint16)
        padded[:, 0] = fid
        return padded, 5123
    return np.asarray(fid, np.float32), 5126


__all__ = ["FACE_QUALITY_CLASS", "face_quality_table", "feature_id_values", "split_per_face"]
