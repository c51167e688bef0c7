"""A rebuilt region on disk, and the one type the merge takes it as (:class:`RegionMesh`).

::

    regions/{key}/mesh.npz            the rebuilt mesh (format below); absent when the region is
                                      left to the mesh
    regions/{key}/fused.npz           the fused points: xyz (k, 3) float32 campus-local, source (k,)
                                      int8 (0 mesh vertex, 1 MLS point)
    regions/{key}/atlas.jpg           the region's texture atlas (absent when no image sees it)
    regions/{key}/region.json         status ("rebuilt" | "kept"), evidence (defect type), replaced
                                      tiles, figures; written last: its presence marks a complete region
    regions/_occupancy/{tile}.npz     MLS-occupied voxels of a tile (occluders for the texture step)

``mesh.npz`` (numpy, uncompressed)::

    vertices      (n, 3) float32  metres, campus-local
    vertex_id     (n,)   int64    a campus id (storage.vertex_ids: input or split vertex) at its
                                  original position (border vertices: shared with the retained faces,
                                  weld by it); a local id: a new vertex (MLS point, input-surface
                                  sample, or a seam vertex moved onto the MLS surface), unique within
                                  the region, not campus-wide
    vertex_source (n,)   int8     0 original mesh vertex, 1 MLS point, 2 Poisson vertex, 3 sample of
                                  the input surface kept where the MLS saw nothing
    faces         (m, 3) int32    counter-clockwise seen from outside (like the input mesh)
    face_patch    (m,)   int64    patch key of each face's centroid (the partition's rule): the tile of
                                  a face is ``grid.tile_of_keys(face_patch)``
    uv            (m, 3, 2) float32 per-corner atlas coordinates, OBJ convention (origin bottom-left);
                                  NaN for a face no image sees
    face_color    (m, 3) uint8    colour of each face: the image colour, or the original mesh texture's
                                  colour where no image sees it (use it where uv is NaN)
    replaced_tile (r,)   int16    index into region.json "replaced_tiles"
    replaced_row  (r,)   int64    row in that tile's faces.parquet of each original face it replaces

The merge reads them through :func:`region_meshes_for_tile`; its resume decision needs only
:func:`region_files_for_tile` (the same regions' file fingerprints, no array read).
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path, file_fingerprint, write_json_atomic
from storage.contracts.region_plan import plan_grid, plan_path, read_plan_doc, region_dir
from storage.ids import TileId

MESH_FILE, FUSED_FILE, ATLAS_FILE, REGION_FILE = "mesh.npz", "fused.npz", "atlas.jpg", "region.json"
MESH_ARRAYS = {"vertices": np.float32, "vertex_id": np.int64, "vertex_source": np.int8, "faces": np.int32,
               "face_patch": np.int64, "uv": np.float32, "face_color": np.uint8, "replaced_tile": np.int16,
               "replaced_row": np.int64}


@dataclass(frozen=True, eq=False)
class RegionMesh:
    """One rebuilt region as the merge takes it: every face of the region (the merge keeps those its tile
    owns, by its own rule) and what it replaces in the merged tile.

    region: region number (>= 0, ``Region.number``). vertices: (n, 3) float32 metres campus-local.
    faces: (m, 3) int64 into vertices. replaced_patches: (p,) int64 packed patch keys whose original faces
    go. vertex_ids: (n,) int64 campus vertex id of each vertex kept from the original mesh (its border
    vertices: they weld exactly to the retained faces), < 0 for a new vertex; None: all new.
    atlas: the region's atlas image path, or None. corner_uv: (m, 3, 2) float32 per-corner uv into
    ``atlas`` (OBJ convention; NaN: a face no image sees), or None. face_colors: (m, 3) uint8 sRGB for
    faces not textured, or None (grey). replaced_rows: (r,) int64 rows of the merged tile's faces table
    the region replaces, or None (valid for the store the region was built from). fingerprint: the
    region's content identity for resume ("": hashed from the arrays). region_id: the region's key
    (its folder); defect_type: its evidence verdict.
    """

    region: int
    vertices: np.ndarray
    faces: np.ndarray
    replaced_patches: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    vertex_ids: np.ndarray | None = None
    atlas: str | None = None
    corner_uv: np.ndarray | None = None
    face_colors: np.ndarray | None = None
    replaced_rows: np.ndarray | None = None
    fingerprint: str = ""
    region_id: str = ""
    defect_type: str = ""

    def __post_init__(self):
        n, m = len(self.vertices), len(self.faces)
        bad = [
            (self.region >= 0, "region must be >= 0"),
            (np.shape(self.vertices) == (n, 3), "vertices must be (n, 3)"),
            (np.shape(self.faces) == (m, 3), "faces must be (m, 3)"),
            (m == 0 or (np.min(self.faces) >= 0 and np.max(self.faces) < n), "faces index outside the vertices"),
            (np.ndim(self.replaced_patches) == 1, "replaced_patches must be (p,)"),
            (self.vertex_ids is None or np.shape(self.vertex_ids) == (n,), "vertex_ids must be (n,)"),
            (self.atlas is None or self.corner_uv is not None, "an atlas needs corner_uv"),
            (self.corner_uv is None or np.shape(self.corner_uv) == (m, 3, 2), "corner_uv must be (m, 3, 2)"),
            (self.face_colors is None or np.shape(self.face_colors) == (m, 3), "face_colors must be (m, 3)"),
            (self.replaced_rows is None or np.ndim(self.replaced_rows) == 1, "replaced_rows must be (r,)"),
        ]  # fmt: skip
        for ok, problem in bad:
            if not ok:
                raise ValueError(f"rebuilt region {self.region}: {problem}")

    def content_fingerprint(self) -> str:
        """``fingerprint`` if the reader gave one, else a hash of the arrays and the atlas file."""
        if self.fingerprint:
            return self.fingerprint
        h = hashlib.sha256(str(self.region).encode())
        for a in (self.vertices, self.faces, self.replaced_patches, self.vertex_ids, self.corner_uv,
                  self.face_colors, self.replaced_rows):
            h.update(b"-" if a is None else np.ascontiguousarray(a).tobytes() + str(a.shape).encode())
        if self.atlas is not None:
            h.update(self.atlas.encode())
            with contextlib.suppress(OSError):
                h.update(file_fingerprint(self.atlas).encode())
        return h.hexdigest()[:32]


def clear_region(out_dir: Path) -> None:
    """Remove a region's files, ``region.json`` (the 'complete' marker) first."""
    for name in (REGION_FILE, MESH_FILE, FUSED_FILE, ATLAS_FILE):
        (out_dir / name).unlink(missing_ok=True)


def write_region_mesh(out_dir: Path, mesh: dict[str, np.ndarray], fused_xyz: np.ndarray, fused_source: np.ndarray,
                      atlas_image: np.ndarray | None) -> list[str]:
    """Write ``mesh.npz`` (the arrays of :data:`MESH_ARRAYS`, cast to their dtypes), ``fused.npz`` and, given an
    (h, w, 3) uint8 image, ``atlas.jpg``. Returns the names written."""
    from PIL import Image

    missing = set(MESH_ARRAYS) - set(mesh)
    if missing:
        raise ValueError(f"region mesh without {sorted(missing)}")
    with atomic_path(out_dir / MESH_FILE) as tmp:
        np.savez(tmp, **{k: np.asarray(mesh[k], dt) for k, dt in MESH_ARRAYS.items()})
    with atomic_path(out_dir / FUSED_FILE) as tmp:
        np.savez(tmp, xyz=np.asarray(fused_xyz, np.float32), source=np.asarray(fused_source, np.int8))
    names = [MESH_FILE, FUSED_FILE]
    if atlas_image is not None:
        with atomic_path(out_dir / ATLAS_FILE) as tmp:
            Image.fromarray(atlas_image).save(tmp, format="JPEG", quality=90)
        names.append(ATLAS_FILE)
    return names


def write_region_doc(out_dir: Path, doc: dict) -> None:
    """Write ``region.json``, last: it marks the region complete."""
    write_json_atomic(out_dir / REGION_FILE, doc, indent=None)


def _rebuilt_meta(d: Path) -> dict | None:
    """A region folder's region.json when the region was rebuilt; None when unreadable or not rebuilt."""
    try:
        meta = json.loads((d / REGION_FILE).read_text())
    except (OSError, ValueError):
        return None
    return meta if meta.get("status") == "rebuilt" else None


def region_meshes_for_tile(root: str | Path, tile: TileId) -> list[RegionMesh]:
    """The rebuilt regions of the current plan that reach into ``tile`` (work dir at ``root``).

    Only complete regions (``region.json`` present, status "rebuilt") count; a region left to the mesh
    replaces nothing. A region reaches into the tile when one of its faces lies in a patch of the tile
    or it replaces one of the tile's faces; it comes whole (every face), with ``replaced_rows`` the rows of
    this tile's faces table it replaces and a fingerprint of its files.
    """
    doc = read_plan_doc(root)
    if doc is None:
        return []
    grid = plan_grid(doc)
    out = []
    for entry in doc["regions"]:
        if tile.key not in entry["tiles"]:
            continue
        d = region_dir(root, entry["key"])
        meta = _rebuilt_meta(d)
        if meta is None:
            continue
        with np.load(d / MESH_FILE) as z:
            arr = {k: z[k] for k in z.files}
        ftile = grid.tile_of_keys(arr["face_patch"])
        owns = ((ftile[:, 0] == tile.ix) & (ftile[:, 1] == tile.iy)).any()
        ti = meta["replaced_tiles"].index(tile.key) if tile.key in meta["replaced_tiles"] else -1
        rows = arr["replaced_row"][arr["replaced_tile"] == ti] if ti >= 0 else np.zeros(0, np.int64)
        if not owns and not len(rows):
            continue
        atlas = d / meta["atlas"] if meta.get("atlas") else None
        fp = ":".join(file_fingerprint(p) for p in (d / MESH_FILE, d / REGION_FILE, atlas) if p is not None)
        out.append(RegionMesh(region=int(entry["number"]), vertices=arr["vertices"].astype(np.float32),
                              faces=arr["faces"].astype(np.int64), vertex_ids=arr["vertex_id"].astype(np.int64),
                              atlas=None if atlas is None else str(atlas), corner_uv=arr["uv"].astype(np.float32),
                              face_colors=arr["face_color"].astype(np.uint8),
                              replaced_rows=np.sort(rows).astype(np.int64), fingerprint=f"{tile.key}:{fp}",
                              region_id=entry["key"], defect_type=meta.get("evidence", {}).get("type", "")))
    return out


@dataclass(frozen=True)
class RegionFiles:
    """A complete rebuilt region as the merge's resume decision sees it, without reading its arrays.

    region: its number (``Region.number``); key: its folder; fingerprint: ``"{tile}:{mesh}:{json}[:{atlas}]"``
    (:func:`storage.atomic.file_fingerprint` of each file), the value :func:`region_meshes_for_tile` gives
    ``RegionMesh.fingerprint`` for the same tile.
    """

    region: int
    key: str
    fingerprint: str


@functools.lru_cache(maxsize=4)
def _tiles_of_plan(path: str, ino: int, mtime_ns: int, size: int) -> dict[str, tuple[tuple[int, str], ...]]:
    """{tile key: ((number, region key), ...)} of the plan at ``path``, cached per file identity (the plan
    is replaced atomically: a new plan is a new inode), so planning T tiles parses it once, not T times."""
    doc = read_plan_doc(Path(path).parents[1])
    out: dict[str, list[tuple[int, str]]] = {}
    for entry in [] if doc is None else doc["regions"]:
        for t in entry["tiles"]:
            out.setdefault(t, []).append((int(entry["number"]), entry["key"]))
    return {t: tuple(v) for t, v in out.items()}


def region_files_for_tile(root: str | Path, tile: TileId) -> list[RegionFiles]:
    """The complete rebuilt regions of the current plan that list ``tile``, fingerprinted by their files
    only: no mesh is loaded (a resume decision costs a stat and two small reads per region).

    A superset of :func:`region_meshes_for_tile`: it also names a region the plan lists the tile for
    (context patches) that neither owns a face in it nor replaces one of its rows. Raises OSError when
    a complete region misses its mesh or atlas (as loading it would).
    """
    p = plan_path(root)
    try:
        st = p.stat()
    except FileNotFoundError:
        return []
    out = []
    for number, key in _tiles_of_plan(str(p), st.st_ino, st.st_mtime_ns, st.st_size).get(tile.key, ()):
        d = region_dir(root, key)
        meta = _rebuilt_meta(d)
        if meta is None:
            continue
        atlas = d / meta["atlas"] if meta.get("atlas") else None
        fp = ":".join(file_fingerprint(f) for f in (d / MESH_FILE, d / REGION_FILE, atlas) if f is not None)
        out.append(RegionFiles(number, key, f"{tile.key}:{fp}"))
    return out
