"""Face soups: faces as unshared corners with weld keys and attributes, welded into a TileMesh.

The store's faces and each rebuilt region become a :class:`FaceSoup`; :func:`weld_soup` welds their
concatenation by key (:mod:`tasks.merge.weld`) into the export's :class:`storage.contracts.tile_mesh.TileMesh`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from storage.contracts.region_mesh import RegionMesh
from storage.contracts.tile_mesh import GRADE_BAD, NO_REGION, SOURCE_MESH, SOURCE_REBUILT, TileMesh
from storage.vertex_ids import MISSING, is_campus_id, local_ids
from tasks.merge.weld import face_keep_mask, weld_corners, weld_keys

REBUILT_GREY = np.array([170, 170, 170], np.uint8)  # rebuilt faces with neither atlas nor colours


@dataclass(frozen=True, eq=False)
class FaceSoup:
    """Faces as unshared corners, before welding.

    xyz: (m, 3, 3) float32 metres campus-local. keys: (m, 3) int64 weld key per corner (campus vertex
    id, or a region's own key < 0). uv: (m, 3, 2) float32 (0 where untextured). texture: (m,) int32
    index into the merge's texture list, -1 untextured. color: (m, 3, 3) uint8 per corner.
    grade / source: (m,) int8; region: (m,) int32 (storage.contracts.tile_mesh conventions).
    """

    xyz: np.ndarray
    keys: np.ndarray
    uv: np.ndarray
    texture: np.ndarray
    color: np.ndarray
    grade: np.ndarray
    source: np.ndarray
    region: np.ndarray

    @property
    def n_faces(self) -> int:
        return len(self.keys)

    def take(self, rows: np.ndarray) -> FaceSoup:
        return FaceSoup(**{k: getattr(self, k)[rows] for k in _SOUP_FIELDS})


_SOUP_FIELDS = ("xyz", "keys", "uv", "texture", "color", "grade", "source", "region")


def concat_soups(parts: Sequence[FaceSoup]) -> FaceSoup:
    return FaceSoup(**{k: np.concatenate([getattr(p, k) for p in parts]) for k in _SOUP_FIELDS})


def _position_keys(xyz: np.ndarray, base: int) -> np.ndarray:
    """(c, 3) float32 corners -> (c,) int64 keys equal for bit-identical positions, all <= base."""
    bits = np.ascontiguousarray(xyz, np.float32).view(np.uint32).astype(np.int64)
    _, inverse = np.unique(bits, axis=0, return_inverse=True)
    return base - inverse.reshape(-1)


def store_soup(cols: dict[str, np.ndarray], grade: np.ndarray, rows: np.ndarray | None = None) -> FaceSoup:
    """The soup of patch-store face rows.

    cols: store face columns (:data:`tasks.merge.tile.STORE_FACE_COLUMNS` but patch), (m,) each.
    grade: (k,) int8 per face of the soup. rows: (k,) int64 the rows of ``cols`` to take (each column is
    indexed as it is used: no copy of the whole table), None: all (k = m). A face is textured when its
    texture index is >= 0 and its three uv are finite. Corners without a vertex id (-1: an input written
    without ids) weld by exact position.
    """
    col = (lambda name: cols[name]) if rows is None else (lambda name: cols[name][rows])
    xyz = np.stack([np.stack([col(f"{a}{v}") for a in "xyz"], axis=1) for v in range(3)], axis=1)
    keys = np.stack([col(f"vid{v}") for v in range(3)], axis=1).astype(np.int64, copy=False)
    if (keys == MISSING).any():  # no ids: weld exactly coincident corners, in a key range of their own
        missing = keys == MISSING
        keys = keys.copy()
        keys[missing] = _position_keys(xyz[missing], int(local_ids(np.zeros(1), "merge_position")[0]))
    uv = np.stack([np.stack([col(f"{a}{v}") for a in "uv"], axis=1) for v in range(3)], axis=1)
    finite = np.isfinite(uv).all(axis=(1, 2))
    tex = col("texture")
    texture = np.where(finite & (tex >= 0), tex, -1).astype(np.int32)
    uv = np.where((texture >= 0)[:, None, None], uv, np.float32(0)).astype(np.float32, copy=False)
    rgb = np.stack([col("red"), col("green"), col("blue")], axis=1).astype(np.uint8, copy=False)
    m = len(keys)
    return FaceSoup(xyz=xyz, keys=keys, uv=uv, texture=texture, color=np.repeat(rgb[:, None, :], 3, axis=1),
                    grade=np.asarray(grade, np.int8), source=np.full(m, SOURCE_MESH, np.int8),
                    region=np.full(m, NO_REGION, np.int32))  # fmt: skip


def region_soup(r: RegionMesh, texture_index: int, rank: int = 0) -> FaceSoup:
    """The soup of one rebuilt region's faces. texture_index: its atlas in the merge's texture list
    (ignored without an atlas). Vertices without a campus id (:mod:`storage.vertex_ids`: new ones) get
    keys of the merge's own block, ``local_ids(rank << 32 | index, "merge_own")``, rank: the region's place
    among the merge's regions (distinct per region, never a campus id)."""
    f = r.faces
    m = len(f)
    ids = np.full(len(r.vertices), -1, np.int64) if r.vertex_ids is None else r.vertex_ids
    own = local_ids((np.int64(rank) << 32) | np.arange(len(r.vertices), dtype=np.int64), "merge_own")
    keys = np.where(is_campus_id(ids), ids, own)[f]
    uv = np.zeros((m, 3, 2), np.float32) if r.corner_uv is None else r.corner_uv
    textured = np.full(m, r.atlas is not None) & np.isfinite(uv).all(axis=(1, 2))
    uv = np.where(textured[:, None, None], uv, np.float32(0)).astype(np.float32, copy=False)
    face_colors = np.broadcast_to(REBUILT_GREY, (m, 3)) if r.face_colors is None else r.face_colors
    corner_color = np.repeat(np.asarray(face_colors, np.uint8)[:, None, :], 3, axis=1)
    return FaceSoup(xyz=r.vertices[f], keys=keys, uv=uv, texture=np.where(textured, texture_index, -1).astype(np.int32),
                    color=corner_color, grade=np.full(m, GRADE_BAD, np.int8),
                    source=np.full(m, SOURCE_REBUILT, np.int8), region=np.full(m, r.region, np.int32))  # fmt: skip


# ------------------------------------------------------------------------------ welding a soup


@dataclass(frozen=True)
class WeldStats:
    """Counts of one weld: faces in and out, dropped duplicates / degenerate faces, vertices, seam splits."""

    faces_in: int
    faces_out: int
    duplicates: int
    degenerate: int
    vertices: int
    split_vertices: int


def weld_soup(tile_key: str, soup: FaceSoup, textures: Sequence[str]) -> tuple[TileMesh, WeldStats]:
    """Weld a soup into a TileMesh (see the module docstring). textures: the paths ``soup.texture``
    indexes; the TileMesh keeps only those its faces use, in first-use order of their indices."""
    m = soup.n_faces
    welded = weld_keys(soup.keys.reshape(-1))
    keep = face_keep_mask(welded[0], m)
    f = welded[0].reshape(m, 3)
    degenerate = int(((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])).sum())
    del f
    s = soup
    if not keep.all():
        s = soup.take(np.flatnonzero(keep))
        welded = weld_keys(s.keys.reshape(-1))
    textured = s.texture >= 0
    # texture + colour in one attribute (colour only matters where untextured), uv bits in the other
    rgb = s.color.reshape(-1, 3)
    packed_rgb = (rgb[:, 0].astype(np.uint32) << 16) | (rgb[:, 1].astype(np.uint32) << 8) | rgb[:, 2]
    attr_a = np.repeat((s.texture.astype(np.int64) + 1) << 24, 3)
    attr_a |= np.where(np.repeat(textured, 3), np.uint32(0), packed_rgb)
    del packed_rgb
    attr_a = attr_a[welded[2]]  # in key-sorted order: the kernel then needs no copy of its own
    uv_bits = s.uv.reshape(-1, 2).view(np.uint32)
    attr_b = uv_bits[:, 0].astype(np.int64) << 32
    attr_b |= uv_bits[:, 1]
    attr_b = attr_b[welded[2]]
    w = weld_corners(s.keys.reshape(-1), attr_a, attr_b, welded, attrs_sorted=True)
    del attr_a, attr_b, welded

    used = np.unique(s.texture[textured])
    remap = np.full(len(textures) + 1, -1, np.int16)
    remap[used] = np.arange(len(used), dtype=np.int16)
    face_texture = remap[s.texture]  # -1 stays -1 (remap[-1] is the spare slot)
    any_textured = bool(textured.any())
    mesh = TileMesh(
        tile=tile_key,
        vertices=np.ascontiguousarray(s.xyz.reshape(-1, 3)[w.position_corner], np.float32),
        faces=w.faces, face_texture=face_texture.astype(np.int16),
        uv=np.ascontiguousarray(s.uv.reshape(-1, 2)[w.corner], np.float32) if any_textured else None,
        textures=[str(textures[i]) for i in used], vertex_colors=np.ascontiguousarray(s.color.reshape(-1, 3)[w.corner]),
        grade=s.grade, source=s.source, region=s.region,
    )  # fmt: skip
    stats = WeldStats(faces_in=m, faces_out=mesh.n_faces, duplicates=m - int(keep.sum()) - degenerate,
                      degenerate=degenerate, vertices=mesh.n_vertices, split_vertices=w.n_split)
    return mesh, stats
