"""The synthetic scene: the contract between the synth generators.

All geometry here is in the *mesh frame*: campus-local metres, float64, x east, y north, z up,
z = 0 at the mean terrain height. The world (projected CRS) position is ``frame.origin + local``.
The MLS cloud is written in a frame perturbed from this one by the known similarity transform
recorded in ``truth/registration.json``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from tasks.geometry.triangles import face_areas


class FaceClass(IntEnum):
    """Semantic class of a truth face (uint8 in arrays)."""

    GROUND = 0
    ROAD = 1
    WALL = 2
    ROOF = 3
    GLASS = 4  # window and door panes, recessed 0.1-0.3 m behind the wall plane
    FRAME = 5  # window/door reveals and frames
    BALCONY = 6  # balconies, ledges, cornices
    EAVE = 7  # underside of roof overhangs


class OccluderClass(IntEnum):
    TREE = 0
    CAR = 1
    PEDESTRIAN = 2
    FENCE = 3


# Default appearance per class, RGB uint8 (walls are varied per building).
CLASS_COLOR = {
    FaceClass.GROUND: (112, 128, 88),
    FaceClass.ROAD: (70, 70, 74),
    FaceClass.WALL: (196, 180, 160),
    FaceClass.ROOF: (150, 70, 60),
    FaceClass.GLASS: (60, 80, 105),
    FaceClass.FRAME: (230, 230, 225),
    FaceClass.BALCONY: (170, 170, 170),
    FaceClass.EAVE: (120, 110, 100),
}


@dataclass
class Building:
    """One building's parameters (for reporting and for defect placement).

    footprint: (k, 2) float64, counter-clockwise polygon, metres.
    """

    id: int
    footprint: np.ndarray
    storeys: int
    storey_height_m: float
    roof: str  # "flat" | "gable" | "hip"
    eave_overhang_m: float
    height_m: float  # wall height (top of the walls, without the roof)


@dataclass
class Mesh:
    """A triangle mesh with per-face attributes.

    vertices: (n, 3) float64 metres; faces: (m, 3) int64; face_class: (m,) uint8 FaceClass;
    face_building: (m,) int32, -1 for terrain/roads; face_color: (m, 3) uint8 RGB.
    """

    vertices: np.ndarray
    faces: np.ndarray
    face_class: np.ndarray
    face_building: np.ndarray
    face_color: np.ndarray

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    def triangles(self) -> np.ndarray:
        """(m, 3, 3) float64."""
        return self.vertices[self.faces]

    def face_areas(self) -> np.ndarray:
        """(m,) m² (:func:`tasks.geometry.triangles.face_areas`)."""
        return face_areas(self.vertices, self.faces)

    def face_normals(self) -> np.ndarray:
        t = self.triangles()
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    @staticmethod
    def concat(meshes: list[Mesh]) -> Mesh:
        meshes = [m for m in meshes if m.n_faces]
        if not meshes:
            return Mesh.empty()
        offs = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
        return Mesh(
            vertices=np.concatenate([m.vertices for m in meshes]),
            faces=np.concatenate([m.faces + o for m, o in zip(meshes, offs)]),
            face_class=np.concatenate([m.face_class for m in meshes]),
            face_building=np.concatenate([m.face_building for m in meshes]),
            face_color=np.concatenate([m.face_color for m in meshes]),
        )

    @staticmethod
    def empty() -> Mesh:
        return Mesh(
            np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.uint8),
            np.zeros(0, np.int32), np.zeros((0, 3), np.uint8),
        )


def soup_to_mesh(parts, building: int, tol: float = 1e-6) -> Mesh:
    """[(triangles (m, 3, 3), class, rgb (3,)), ...] -> welded Mesh (vertices merged within ``tol`` m)."""
    tris = np.concatenate([p[0] for p in parts])
    key = np.round(tris.reshape(-1, 3) / tol).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return Mesh(vertices=tris.reshape(-1, 3)[first], faces=inv.reshape(-1, 3).astype(np.int64),
                face_class=np.concatenate([np.full(len(p[0]), p[1], np.uint8) for p in parts]),
                face_building=np.full(len(tris), building, np.int32),
                face_color=np.concatenate([np.tile(np.asarray(p[2], np.uint8), (len(p[0]), 1)) for p in parts]))


@dataclass
class Occluders:
    """Things in front of facades that the MLS and cameras see but the truth excludes.

    mesh.face_class holds OccluderClass values here; face_building holds the occluder instance id.
    """

    mesh: Mesh


@dataclass
class Scene:
    """Truth geometry of a synthetic campus (or of one tile of it).

    roads: list of (k, 2) float64 polylines (road centre lines, metres) the MLS vehicle drives.
    extent: (xmin, ymin, xmax, ymax) metres, campus-local.
    """

    truth: Mesh
    occluders: Occluders
    buildings: list[Building]
    roads: list[np.ndarray]
    extent: tuple[float, float, float, float]
    meta: dict = field(default_factory=dict)
