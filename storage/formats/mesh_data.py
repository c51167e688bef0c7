"""``MeshData``, the value every mesh reader returns, and the pure face checks all readers apply.

vertices: (n, 3) float64 WORLD metres; faces: (m, 3) int64. Readers live in :mod:`storage.formats.meshes`
(the public API) and :mod:`storage.formats.obj` (OBJ + MTL).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field, replace

import numpy as np

DEGENERATE_AREA_M2 = 1e-12


@dataclass
class MeshData:
    """A triangle mesh with optional texture and colours.

    vertices: (n, 3) float64 world metres. faces: (m, 3) int64 indices into vertices.
    uv: (m, 3, 2) float32 per-corner texture coordinates (OBJ convention) or None.
    face_texture: (m,) int16 index into ``textures``, -1 for an untextured face, or None.
    textures: image references: absolute file paths, or "<file.glb>#image<k>" for images embedded in
        a GLB, whose pixels are in ``embedded_textures`` under the same key ((H, W, 3) uint8).
    face_colors / vertex_colors: (m, 3) / (n, 3) uint8 RGB or None.
    n_degenerate_dropped, n_duplicate_dropped: faces removed on reading; n_nonmanifold_edges: edges
        shared by more than two of the kept faces (kept, only counted).
    warnings: one line per problem the reader worked around ("<file>: dropped 3 of 134,116 faces: ...",
        "<file>: material library ... not found; ..."), each naming the file; the caller reports them.
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray | None = None
    face_texture: np.ndarray | None = None
    textures: list[str] = field(default_factory=list)
    face_colors: np.ndarray | None = None
    vertex_colors: np.ndarray | None = None
    source: str = ""
    n_degenerate_dropped: int = 0
    n_duplicate_dropped: int = 0
    n_nonmanifold_edges: int = 0
    embedded_textures: dict[str, np.ndarray] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def select_faces(self, keep: np.ndarray) -> MeshData:
        """The same mesh with only faces ``keep`` (boolean mask or indices); vertices untouched."""
        pick = lambda a: None if a is None else a[keep]
        return replace(
            self, faces=self.faces[keep], uv=pick(self.uv), face_texture=pick(self.face_texture),
            face_colors=pick(self.face_colors),
        )  # fmt: skip

    @staticmethod
    def concat(meshes: Iterable[MeshData], source: str = "") -> MeshData:
        """One mesh of all ``meshes``: face indices and texture indices shifted, identical texture
        references merged, drop/non-manifold counts summed, warnings joined. A colour array survives only if every
        part has one; UVs of parts without any are zero with face_texture -1."""
        meshes = list(meshes)
        textures: dict[str, int] = {}
        verts, faces, uvs, ftex, base = [], [], [], [], 0
        any_uv = any(m.uv is not None for m in meshes)
        any_tex = any(m.face_texture is not None for m in meshes)
        for m in meshes:
            verts.append(m.vertices)
            faces.append(m.faces + base)
            base += len(m.vertices)
            if any_uv:
                uvs.append(m.uv if m.uv is not None else np.zeros((m.n_faces, 3, 2), np.float32))
            if any_tex:
                remap = np.array([textures.setdefault(t, len(textures)) for t in m.textures] + [-1], np.int16)
                local = m.face_texture if m.face_texture is not None else np.full(m.n_faces, -1, np.int16)
                ftex.append(remap[local])  # -1 indexes the trailing -1
        cat = lambda name: (
            np.concatenate([getattr(m, name) for m in meshes])
            if meshes and all(getattr(m, name) is not None for m in meshes) else None
        )  # fmt: skip
        return MeshData(
            vertices=np.concatenate(verts) if verts else np.zeros((0, 3)),
            faces=np.concatenate(faces) if faces else np.zeros((0, 3), np.int64),
            uv=np.concatenate(uvs) if any_uv else None,
            face_texture=np.concatenate(ftex) if any_tex else None,
            textures=list(textures),
            face_colors=cat("face_colors"),
            vertex_colors=cat("vertex_colors"),
            source=source,
            n_degenerate_dropped=sum(m.n_degenerate_dropped for m in meshes),
            n_duplicate_dropped=sum(m.n_duplicate_dropped for m in meshes),
            n_nonmanifold_edges=sum(m.n_nonmanifold_edges for m in meshes),
            embedded_textures={k: v for m in meshes for k, v in m.embedded_textures.items()},
            warnings=[w for m in meshes for w in m.warnings],
        )


# --- pure face checks ------------------------------------------------------------------------------


def degenerate_faces(vertices: np.ndarray, faces: np.ndarray, min_area_m2: float = DEGENERATE_AREA_M2):
    """(m,) bool: faces with a repeated vertex id or area below ``min_area_m2``.

    vertices: (n, 3) float64 metres; faces: (m, 3) int64. Edges are differenced before the cross
    product, so large world coordinates do not cost precision.
    """
    f = faces
    repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
    v0 = vertices[f[:, 0]]
    area = 0.5 * np.linalg.norm(np.cross(vertices[f[:, 1]] - v0, vertices[f[:, 2]] - v0), axis=1)
    return repeated | ~(area >= min_area_m2)


def unusable_faces(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Faces no reader can use: ((m,) bool out of range, (m,) bool touching a NaN/inf vertex).

    vertices: (n, 3) float64; faces: (m, 3) int64. A face with an index < 0 or >= n is out of range (and
    not also counted as NaN); the others touch a non-finite vertex if any of their three does.

    >>> v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [np.nan, 0, 0]])
    >>> out, nan = unusable_faces(v, np.array([[0, 1, 2], [0, 1, 3], [0, 1, 9], [-1, 1, 3]]))
    >>> out.tolist(), nan.tolist()
    ([False, False, True, True], [False, True, False, False])
    """
    out = ((faces < 0) | (faces >= len(vertices))).any(axis=1)
    finite = np.isfinite(vertices).all(axis=1)
    safe = np.where(out[:, None], 0, faces)
    nan = ~out & ~finite[safe].all(axis=1) if len(vertices) else np.zeros(len(faces), bool)
    return out, nan


def duplicate_faces(faces: np.ndarray) -> np.ndarray:
    """(m,) bool: faces whose vertex-id set already appeared earlier (either winding)."""
    if len(faces) == 0:
        return np.zeros(0, bool)
    key = np.sort(faces, axis=1)
    order = np.lexsort(key.T[::-1])  # stable: the first of equal faces comes first
    ordered = key[order]
    same_as_previous = np.zeros(len(faces), bool)
    same_as_previous[1:] = (ordered[1:] == ordered[:-1]).all(axis=1)
    dup = np.zeros(len(faces), bool)
    dup[order] = same_as_previous
    return dup


def count_nonmanifold_edges(faces: np.ndarray) -> int:
    """Number of undirected edges used by more than two faces. faces: (m, 3) int64."""
    if len(faces) == 0:
        return 0
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    key = edges[:, 0] * (int(edges.max()) + 1) + edges[:, 1]  # one int64 per undirected edge
    _, counts = np.unique(key, return_counts=True)
    return int((counts > 2).sum())


__all__ = ["DEGENERATE_AREA_M2", "MeshData", "count_nonmanifold_edges", "degenerate_faces", "duplicate_faces",
           "unusable_faces"]
