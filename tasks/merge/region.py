"""The contract between repair and merge: what merge needs of a rebuilt region.

Repair's own type satisfies :class:`RebuiltRegion` by having the attributes; :meth:`RegionMesh.of` casts
and checks it. See :mod:`tasks.merge.stage` for how the fields are used (``replaced_patches`` decide which
original faces go, ``vertex_ids`` weld the region's kept border vertices to the retained mesh).
"""

from __future__ import annotations

import contextlib
import hashlib
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from storage.atomic import file_fingerprint


@runtime_checkable
class RebuiltRegion(Protocol):
    """What merge needs of one rebuilt region; repair's own type satisfies it by having these attributes.

    Required: ``region`` (int, RegionId.n), ``vertices`` ((n, 3) float32 metres campus-local), ``faces``
    ((m, 3) int into vertices), ``replaced_patches`` ((p,) int64 packed keys of the patches, in any tile,
    whose original faces the region replaces). Optional (read with ``getattr``, see :class:`RegionMesh`):
    ``vertex_ids``, ``uv``, ``atlas``, ``colors``, ``textured``, ``replaced_faces``, ``fingerprint``.
    """

    region: int
    vertices: np.ndarray
    faces: np.ndarray
    replaced_patches: np.ndarray


@dataclass(frozen=True, eq=False)
class RegionMesh:
    """One rebuilt region as merge takes it.

    region: region number (>= 0). vertices: (n, 3) float32 metres campus-local. faces: (m, 3) int64.
    replaced_patches: (p,) int64 packed patch keys (``PatchGrid.pack``) whose original faces go.
    vertex_ids: (n,) int64 campus vertex id of each vertex kept from the original mesh (its border
    vertices: they weld exactly to the retained faces), -1 for a new vertex; None: all new.
    uv: (n, 2) float32 per vertex (OBJ convention) into ``atlas`` (a JPEG/PNG path), or None.
    colors: (n, 3) uint8 sRGB for faces not textured, or None (grey).
    textured: (m,) bool, which faces use the atlas (the others, e.g. faces no camera saw, use
    ``colors``); None: every face when there is an atlas.
    replaced_faces: (k, 2) int64 (source, src_face) of further original faces the region replaces
    (beyond those of ``replaced_patches``), or None.
    replaced_rows: (r,) int64 rows of the merged tile's faces table the region replaces, or None
    (repair names the faces it replaces by row; valid for the store the region was built from).
    corner_uv: (m, 3, 2) float32 per-corner uv into ``atlas`` (NaN: untextured), instead of ``uv``.
    face_colors: (m, 3) uint8 per-face sRGB, instead of ``colors``.
    fingerprint: the region's content identity for resume ("" : hashed from the arrays here).
    """

    region: int
    vertices: np.ndarray
    faces: np.ndarray
    replaced_patches: np.ndarray
    vertex_ids: np.ndarray | None = None
    uv: np.ndarray | None = None
    atlas: str | None = None
    colors: np.ndarray | None = None
    textured: np.ndarray | None = None
    replaced_faces: np.ndarray | None = None
    replaced_rows: np.ndarray | None = None
    corner_uv: np.ndarray | None = None
    face_colors: np.ndarray | None = None
    fingerprint: str = ""

    def __post_init__(self):
        n, m = len(self.vertices), len(self.faces)
        bad = [
            (self.region >= 0, "region must be >= 0"),
            (np.shape(self.vertices) == (n, 3), "vertices must be (n, 3)"),
            (np.shape(self.faces) == (m, 3), "faces must be (m, 3)"),
            (m == 0 or (np.min(self.faces) >= 0 and np.max(self.faces) < n), "faces index outside the vertices"),
            (np.ndim(self.replaced_patches) == 1, "replaced_patches must be (p,)"),
            (self.vertex_ids is None or np.shape(self.vertex_ids) == (n,), "vertex_ids must be (n,)"),
            (self.uv is None or np.shape(self.uv) == (n, 2), "uv must be (n, 2)"),
            (self.colors is None or np.shape(self.colors) == (n, 3), "colors must be (n, 3)"),
            (self.textured is None or np.shape(self.textured) == (m,), "textured must be (m,)"),
            (self.atlas is None or self.uv is not None or self.corner_uv is not None, "an atlas needs uv"),
            (self.corner_uv is None or np.shape(self.corner_uv) == (m, 3, 2), "corner_uv must be (m, 3, 2)"),
            (self.face_colors is None or np.shape(self.face_colors) == (m, 3), "face_colors must be (m, 3)"),
            (self.replaced_rows is None or np.ndim(self.replaced_rows) == 1, "replaced_rows must be (r,)"),
            (self.replaced_faces is None or np.shape(self.replaced_faces)[1:] == (2,), "replaced_faces must be (k, 2)"),
        ]  # fmt: skip
        for ok, problem in bad:
            if not ok:
                raise ValueError(f"rebuilt region {self.region}: {problem}")

    @classmethod
    def of(cls, obj) -> RegionMesh:
        """A RegionMesh of any object with the attributes of :class:`RebuiltRegion` (arrays cast)."""
        if isinstance(obj, RegionMesh):
            return obj
        opt = lambda name, dtype: None if getattr(obj, name, None) is None else np.asarray(getattr(obj, name), dtype)
        atlas = getattr(obj, "atlas", None)
        return cls(region=int(obj.region), vertices=np.asarray(obj.vertices, np.float32),
                   faces=np.asarray(obj.faces, np.int64).reshape(-1, 3),
                   replaced_patches=np.asarray(obj.replaced_patches, np.int64).reshape(-1),
                   vertex_ids=opt("vertex_ids", np.int64), uv=opt("uv", np.float32),
                   atlas=None if atlas is None else str(atlas), colors=opt("colors", np.uint8),
                   textured=opt("textured", bool), replaced_faces=opt("replaced_faces", np.int64),
                   replaced_rows=opt("replaced_rows", np.int64), corner_uv=opt("corner_uv", np.float32),
                   face_colors=opt("face_colors", np.uint8),
                   fingerprint=str(getattr(obj, "fingerprint", "") or ""))  # fmt: skip

    def content_fingerprint(self) -> str:
        """``fingerprint`` if repair gave one, else a hash of the arrays and the atlas file."""
        if self.fingerprint:
            return self.fingerprint
        h = hashlib.sha256(str(self.region).encode())
        for a in (self.vertices, self.faces, self.replaced_patches, self.vertex_ids, self.uv, self.colors,
                  self.textured, self.replaced_faces, self.replaced_rows, self.corner_uv, self.face_colors):
            h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes() + str(a.shape).encode())
        if self.atlas is not None:
            h.update(self.atlas.encode())
            with contextlib.suppress(OSError):
                h.update(file_fingerprint(self.atlas).encode())
        return h.hexdigest()[:32]
