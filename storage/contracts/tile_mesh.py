"""The merged mesh of one ground tile: the contract between the merge stage and export.

On disk, per tile::

    tiles/{ix}_{iy}/merged.npz     the arrays below (numpy .npz, uncompressed, written atomically)
    tiles/{ix}_{iy}/merged.json    tile key, texture paths, counts, schema version (written last)

Texture images are referenced, not copied: ``textures`` are JPEG/PNG paths, stored relative to the
tile folder when they lie inside the work dir (so a work dir can be moved) and absolute otherwise;
``read_tile_mesh`` returns absolute paths. ``merged.json`` is renamed into place after the ``.npz``,
so a reader that finds it finds a complete pair.

Frames and conventions:
    vertices are float32 metres campus-local (offsets from ``CampusFrame.origin``, axes of the projected
    CRS: x east(ing), y north(ing), z up); ``uv`` follows the OBJ convention (origin bottom-left, v up),
    one pair per vertex (vertices are split at texture seams).
"""

from __future__ import annotations

import json
import os
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage import recorded
from storage.atomic import atomic_path, file_fingerprint, file_sha256, read_json, write_json_atomic
from storage.errors import InputError
from storage.inputs.location import is_url, split_embedded
from storage.inputs.remote import url_fingerprint

TILE_MESH_SCHEMA_VERSION = 1
GRADE_GOOD, GRADE_BAD, GRADE_UNKNOWN = 0, 1, -1
SOURCE_MESH, SOURCE_REBUILT = 0, 1
NO_REGION = -1

_ARRAYS = ("vertices", "faces", "uv", "face_texture", "vertex_colors", "grade", "source", "region",
           "face_deviation", "face_score")


@dataclass(frozen=True, eq=False)
class TileMesh:
    """One ground tile's clean mesh with per-face provenance.

    tile: key "ix_iy". vertices: (n, 3) float32 metres campus-local. faces: (m, 3) int32.
    uv: (n, 2) float32 per vertex (OBJ convention) or None. face_texture: (m,) int16 index into
    ``textures``, -1 for an untextured face. textures: JPEG/PNG paths. vertex_colors: (n, 3) uint8 RGB
    (used by untextured faces) or None. grade: (m,) int8 (0 good, 1 bad, -1 unknown). source: (m,) int8
    (0 original mesh, 1 rebuilt). region: (m,) int32 region number, -1 for none. face_deviation: (m,)
    float32 metres, the signed scan-to-model distance of the MLS points nearest to each face (positive: the
    scan in front of the face), NaN where no point is near, or None. face_score: (m,) float32 the grader's
    p(bad) of the patch each face lies in, NaN where the patch was not graded, or None.
    """

    tile: str
    vertices: np.ndarray
    faces: np.ndarray
    face_texture: np.ndarray
    grade: np.ndarray
    source: np.ndarray
    region: np.ndarray
    uv: np.ndarray | None = None
    textures: list[str] = field(default_factory=list)
    vertex_colors: np.ndarray | None = None
    face_deviation: np.ndarray | None = None
    face_score: np.ndarray | None = None

    def __post_init__(self):
        n, m = len(self.vertices), len(self.faces)
        checks = [
            (self.vertices.shape == (n, 3) and self.vertices.dtype == np.float32, "vertices must be (n, 3) float32"),
            (self.faces.shape == (m, 3) and self.faces.dtype == np.int32, "faces must be (m, 3) int32"),
            (self.face_texture.shape == (m,) and self.face_texture.dtype == np.int16, "face_texture must be (m,) int16"),
            (self.grade.shape == (m,) and self.grade.dtype == np.int8, "grade must be (m,) int8"),
            (self.source.shape == (m,) and self.source.dtype == np.int8, "source must be (m,) int8"),
            (self.region.shape == (m,) and self.region.dtype == np.int32, "region must be (m,) int32"),
            (self.uv is None or (self.uv.shape == (n, 2) and self.uv.dtype == np.float32), "uv must be (n, 2) float32"),
            (self.vertex_colors is None or (self.vertex_colors.shape == (n, 3) and self.vertex_colors.dtype == np.uint8),
             "vertex_colors must be (n, 3) uint8"),
            *((getattr(self, k) is None or (getattr(self, k).shape == (m,) and getattr(self, k).dtype == np.float32),
               f"{k} must be (m,) float32") for k in ("face_deviation", "face_score")),
        ]  # fmt: skip
        for ok, problem in checks:
            if not ok:
                raise ValueError(f"TileMesh {self.tile}: {problem}")
        if m and (self.faces.min() < 0 or self.faces.max() >= n):
            raise ValueError(f"TileMesh {self.tile}: face indices out of range for {n} vertices")
        if m and (self.face_texture.max() >= len(self.textures) or self.face_texture.min() < -1):
            raise ValueError(f"TileMesh {self.tile}: face_texture out of range for {len(self.textures)} textures")
        if (self.face_texture >= 0).any() and self.uv is None:
            raise ValueError(f"TileMesh {self.tile}: textured faces need uv")

    @property
    def n_faces(self) -> int:
        return len(self.faces)

    @property
    def n_vertices(self) -> int:
        return len(self.vertices)


def tile_mesh_paths(tile_dir: str | Path) -> tuple[Path, Path]:
    """(merged.npz, merged.json) of a tile folder."""
    tile_dir = Path(tile_dir)
    return tile_dir / "merged.npz", tile_dir / "merged.json"


def write_tile_mesh(tile_dir: str | Path, mesh: TileMesh) -> Path:
    """Write ``mesh`` to ``tile_dir/merged.npz`` + ``merged.json`` atomically; returns the .npz path."""
    tile_dir = Path(tile_dir).absolute()
    npz, meta = tile_mesh_paths(tile_dir)
    arrays = {k: getattr(mesh, k) for k in _ARRAYS if getattr(mesh, k) is not None}
    with atomic_path(npz) as tmp, open(tmp, "wb") as f:
        np.savez(f, **arrays)
    textures = []
    for t in mesh.textures:
        if is_url(t):  # a texture of an input named by URL: staged again wherever it is read
            textures.append(t)
            continue
        p = Path(t).absolute()
        inside = os.path.commonpath([p, tile_dir.parent.parent]) == str(tile_dir.parent.parent)
        textures.append(os.path.relpath(p, tile_dir) if inside else str(p))
    write_json_atomic(meta, {
        "schema_version": TILE_MESH_SCHEMA_VERSION, "tile": mesh.tile, "textures": textures,
        "n_vertices": mesh.n_vertices, "n_faces": mesh.n_faces,
    })  # fmt: skip
    return npz


def texture_refs(tile_dir: str | Path, recorded: list[str]) -> list[str]:
    """merged.json's texture list as references: a URL as it is, a path resolved against ``tile_dir``."""
    return [t if is_url(t) else str((Path(tile_dir) / t).resolve()) for t in recorded]


def texture_fingerprint(ref: str) -> str:
    """Content fingerprint of a texture reference: a URL's ETag and size, a file's size and mtime; an image
    embedded in a mesh container (``<file.glb>#image0``), its container's and the key."""
    if is_url(ref):
        return url_fingerprint(ref)
    emb = split_embedded(ref)
    return file_fingerprint(ref) if emb is None else f"{file_fingerprint(emb[0])}#{emb[1]}"


def _texture_exists(ref: str) -> bool:
    emb = split_embedded(ref)
    return Path(ref if emb is None else emb[0]).is_file()


def tile_mesh_content(tile_dir: str | Path) -> tuple[str, bytes, list[str]]:
    """What a merged tile's content is, for fingerprints: (SHA-256 of merged.npz, merged.json's bytes, the
    content fingerprint of each of its textures)."""
    npz, meta = tile_mesh_paths(tile_dir)
    doc = json.loads(meta.read_text())
    return file_sha256(npz), meta.read_bytes(), [texture_fingerprint(t) for t in texture_refs(tile_dir, doc["textures"])]


def read_tile_mesh(tile_dir: str | Path) -> TileMesh:
    """Read what ``write_tile_mesh`` wrote. Raises InputError naming the file for a missing, corrupt or
    inconsistent tile mesh, or a missing texture image."""
    tile_dir = Path(tile_dir).absolute()
    npz, meta = tile_mesh_paths(tile_dir)
    recorded.ensure_local(npz, meta)  # a work dir on a bucket: downloaded when read
    if not meta.exists() or not npz.exists():
        raise InputError(tile_dir, "no merged mesh (merged.npz + merged.json): run the merge stage first")
    doc = read_json(meta, "no merged mesh metadata: run the merge stage first")
    if doc.get("schema_version") != TILE_MESH_SCHEMA_VERSION:
        raise InputError(meta, f"schema_version {doc.get('schema_version')} is not {TILE_MESH_SCHEMA_VERSION}")
    textures = texture_refs(tile_dir, doc["textures"])
    recorded.ensure_local(*(split_embedded(t)[0] if split_embedded(t) else t for t in textures if not is_url(t)))
    for t in textures:
        if not is_url(t) and not _texture_exists(t):
            raise InputError(meta, f"texture image {t} not found")
    arrays = _load_arrays(npz, _ARRAYS)
    try:
        return TileMesh(tile=doc["tile"], textures=textures, **arrays)
    except (TypeError, ValueError) as e:
        raise InputError(npz, str(e)) from None


def read_tile_arrays(tile_dir: str | Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Only the named arrays of a tile mesh (see :class:`TileMesh`; e.g. ("vertices", "faces", "source",
    "region") for a picture of it), without the others or the texture checks of :func:`read_tile_mesh`.
    Raises InputError naming the file for a missing or unreadable mesh, or a missing or inconsistent array."""
    npz, _ = tile_mesh_paths(Path(tile_dir).absolute())
    recorded.ensure_local(npz)  # a work dir on a bucket: downloaded when read
    if not npz.exists():
        raise InputError(npz.parent, "no merged mesh (merged.npz + merged.json): run the merge stage first")
    arrays = _load_arrays(npz, names)
    missing = [k for k in names if k not in arrays]
    if missing:
        raise InputError(npz, f"no {', '.join(missing)} array")
    if "faces" in arrays and "vertices" in arrays and len(arrays["faces"]) \
            and (arrays["faces"].min() < 0 or arrays["faces"].max() >= len(arrays["vertices"])):
        raise InputError(npz, f"face indices out of range for {len(arrays['vertices'])} vertices")
    m = len(arrays["faces"]) if "faces" in arrays else None
    for k in ("face_texture", "grade", "source", "region", "face_deviation", "face_score"):  # one value per face
        if k in arrays and m is not None and len(arrays[k]) != m:
            raise InputError(npz, f"{k} has {len(arrays[k])} values for {m} faces")
    return arrays


def _load_arrays(npz: Path, names: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The arrays of ``names`` that ``npz`` holds (an .npz reads each array on its own)."""
    try:
        with np.load(npz, allow_pickle=False) as z:
            return {k: z[k] for k in names if k in z.files}
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as e:
        raise InputError(npz, f"unreadable ({type(e).__name__}: {e})") from None
