"""Readers of the texture step's inputs: the vehicle cameras in the campus frame and their images, MLS
occupancy voxels (occluders), and the original mesh textures at reduced size (the colour of faces no image
sees).

The images and the camera file are a config input: ``repair.texture.images`` / ``repair.texture.cameras``
(or ``inputs.images`` / ``inputs.cameras`` when the config has them); the camera file may be a cameras.json,
a COLMAP text model (its folder or images.txt) or a ContextCapture BlocksExchange .xml (``storage.formats.cameras``).
Without either, an ``images`` folder beside the first mesh input is used when it holds a cameras.json (the
synth layout).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from storage.errors import InputError
from storage.formats.arrays import read_arrays, write_arrays
from storage.formats.camera_files import camera_files, read_cameras
from storage.formats.cameras import Camera, CameraSet
from storage.formats.images import read_rgb, read_rgb_reduced
from storage.patches.read import PatchStore
from storage.patches.state import store_fingerprint
from tasks.config import CampusConfig


def camera_paths(cfg: CampusConfig) -> tuple[Path | None, Path | None]:
    """(images folder, camera file) from ``repair.texture`` (or ``inputs.images`` / ``inputs.cameras``
    when the config has them), else an ``images`` folder beside the first mesh input (synth layout) and its
    cameras.json. A COLMAP sparse folder is returned as its images.txt (a file, for fingerprints)."""
    tc = cfg.repair.texture
    images = getattr(cfg.inputs, "images", None) or tc.images
    cams = getattr(cfg.inputs, "cameras", None) or tc.cameras
    if images is None and cams is None and cfg.inputs.mesh:
        guess = Path(cfg.inputs.mesh[0]).parent / "images"
        images = str(guess) if (guess / "cameras.json").exists() else None
    if cams is None and images is not None:
        cams = str(Path(images) / "cameras.json")
    cam_path = Path(cams) if cams else None
    if cam_path is not None and cam_path.is_dir():
        cam_path = camera_files(cam_path)[0]  # a COLMAP folder: its images.txt
    return (Path(images) if images else None), cam_path


def _configured(cfg: CampusConfig) -> bool:
    return bool(getattr(cfg.inputs, "cameras", None) or cfg.repair.texture.cameras)


def _image_folders(cs: CameraSet, path: Path, images: Path | None) -> list[Path]:
    """Where relative image paths are looked up: the images folder when configured; else the camera
    file's folder, and for a COLMAP model (``<project>/sparse/0``) also ``../images`` and ``../../images``."""
    if images is not None:
        return [images]
    out = [path.parent]
    if cs.fmt == "colmap":
        out += [path.parent.parent / "images", path.parent.parent.parent / "images"]
    return out


def _resolve_images(cams: list[Camera], path: Path, folders: list[Path]) -> list[Camera]:
    """Cameras with their image path resolved; cameras whose image is missing are dropped with one warning
    line (InputError when none is found)."""
    def resolve(name: str) -> Path | None:
        cands = [Path(name)] if Path(name).is_absolute() else [f / name for f in folders]
        return next((c for c in cands if c.is_file()), None)

    found = [(c, resolve(c.image)) for c in cams]
    kept = [replace(c, image=str(p)) for c, p in found if p is not None]
    missing = [c.image for c, p in found if p is None]
    where = ", ".join(str(f) for f in folders)
    if not kept:
        raise InputError(path, f"none of its {len(cams)} images was found (looked in {where}; first: "
                               f"{missing[0]!r}); set inputs.images to their folder")
    if missing:
        warnings.warn(f"{path}: {len(missing)} of {len(cams)} camera images not found in {where} "
                      f"(first: {missing[0]!r}); those cameras are not used for texturing", stacklevel=2)
    return kept


def load_cameras(cfg: CampusConfig, doc: dict, frame) -> list[Camera]:
    """Every camera of the camera file in the campus frame ([] when there is none).

    Formats (``storage.formats.camera_files.read_cameras``): cameras.json, a COLMAP text model, a BlocksExchange XML.
    cameras.json: {"frame": "MLS" | "mesh", "frame_origin": [x, y, z] world, "cameras": [...]} with
    X_cam = R (X_world - frame_origin) + t. COLMAP and BlocksExchange poses are world coordinates in the
    campus CRS in the mesh's frame (frame "mesh", frame_origin 0). MLS-frame poses go through the campus
    registration (campus.json), mesh-frame poses only through the origin shift. Raises InputError naming
    the file when it is broken, its CRS differs from the campus's, or none of its images exists.
    """
    from tasks.repair.texture import cameras_to_frame

    images, path = camera_paths(cfg)
    if path is None or (not path.exists() and not _configured(cfg)):
        return []
    cs = _read_cameras_once(path)
    crs = getattr(frame, "crs", None)
    if cs.crs and crs and cs.crs.upper().startswith("EPSG:") and cs.crs.upper() != str(crs).upper():
        raise InputError(path, f"cameras are in {cs.crs}, the campus in {crs}: export them in the campus CRS")
    fo = np.asarray(cs.frame_origin, np.float64)
    oc = np.asarray(frame.origin, np.float64)
    m = np.eye(4)
    if cs.frame == "MLS":
        reg = np.asarray(doc["registration"]["matrix"], np.float64)
        m[:3, :3] = reg[:3, :3]
        m[:3, 3] = reg[:3, :3] @ (fo - oc) + reg[:3, 3]
    else:
        m[:3, 3] = fo - oc
    return _resolve_images(cameras_to_frame(cs.cameras, m), path, _image_folders(cs, path, images))


_CAMERAS: dict = {}  # the last camera file parsed in this process: {(path, stamp): CameraSet}


def _read_cameras_once(path: Path) -> CameraSet:
    """``read_cameras(path)``, parsed once per process while the file stays the same (a worker repairs many
    regions of one campus); the images are looked up again on every call."""
    key = (str(path), _stamp(path))
    if key not in _CAMERAS:
        _CAMERAS.clear()
        _CAMERAS[key] = read_cameras(path)
    return _CAMERAS[key]


def _stamp(path: Path) -> tuple:
    """(size, mtime) of the camera file, or of a COLMAP model's images.txt and cameras.txt."""
    out = []
    for f in camera_files(path):
        try:
            st = f.stat()
            out.append((st.st_size, st.st_mtime_ns))
        except OSError:
            out.append(None)
    return tuple(out)


OCCUPANCY_WINDOW = 4_000_000  # points read at once when a tile's occupancy is built
_PACK_BITS, _PACK_OFFSET = 21, 1 << 20


def voxel_cells(cells: np.ndarray) -> np.ndarray:
    """The distinct rows of (n, 3) int64 voxel indices, sorted as ``np.unique(cells, axis=0)`` sorts them:
    on one packed int64 key per row when every index lies within +-2^20 (a campus-local frame), else rows.

    >>> voxel_cells(np.array([[1, 2, 3], [-1, 0, 5], [1, 2, 3]])).tolist()
    [[-1, 0, 5], [1, 2, 3]]
    """
    cells = np.asarray(cells, np.int64).reshape(-1, 3)
    if not len(cells) or not (np.abs(cells) < _PACK_OFFSET).all():
        return np.unique(cells, axis=0)
    c = cells + _PACK_OFFSET
    key = np.unique((c[:, 0] << 2 * _PACK_BITS) | (c[:, 1] << _PACK_BITS) | c[:, 2])
    mask = (1 << _PACK_BITS) - 1
    return np.stack([key >> 2 * _PACK_BITS, (key >> _PACK_BITS) & mask, key & mask], axis=1) - _PACK_OFFSET


def occupancy(tile_dir: Path, cache: Path, voxel_m: float) -> np.ndarray:
    """(k, 3) float32 centres of a tile's MLS-occupied voxels (``voxel_m`` metres, campus-local), cached in
    ``cache`` (``regions/_occupancy/{tile}.npz``) and rebuilt when the tile's store changes; built from
    windows of ``OCCUPANCY_WINDOW`` points (at real MLS density a whole tile is tens of millions)."""
    fp = store_fingerprint(tile_dir)
    key = (str(cache), fp, voxel_m)
    if key in _OCCUPANCY:  # the regions of a batch share tiles: each tile's voxels are read once per process
        return _OCCUPANCY[key]
    if cache.exists():
        z = read_arrays(cache)
        if str(z["fingerprint"]) == fp and float(z["voxel_m"]) == voxel_m:
            return _remember(key, z["centres"])
    store = PatchStore(tile_dir)
    parts = []
    for lo in range(0, store.n_points, OCCUPANCY_WINDOW):  # bounded memory at any MLS density
        xyz = store.read_rows_stacked("points", ["x", "y", "z"], lo, min(lo + OCCUPANCY_WINDOW, store.n_points))
        parts.append(voxel_cells(np.floor(xyz / voxel_m).astype(np.int64)))
        del xyz
    cells = voxel_cells(np.concatenate(parts)) if parts else np.zeros((0, 3), np.int64)
    centres = ((cells + 0.5) * voxel_m).astype(np.float32)
    write_arrays(cache, {"centres": centres, "fingerprint": np.array(fp), "voxel_m": np.array(voxel_m)})
    return _remember(key, centres)


_OCCUPANCY: dict = {}  # the last few tiles' voxel centres in this process (read-only arrays)
_OCCUPANCY_TILES = 4


def _remember(key: tuple, centres: np.ndarray) -> np.ndarray:
    centres.setflags(write=False)
    _OCCUPANCY.pop(key, None)
    _OCCUPANCY[key] = centres
    while len(_OCCUPANCY) > _OCCUPANCY_TILES:
        _OCCUPANCY.pop(next(iter(_OCCUPANCY)))
    return centres


def image_loader(cams: list) -> Callable[[int], np.ndarray]:
    """load_image(i) -> (h, w, 3) uint8 RGB image of ``cams[i]``, each decoded once."""
    images: dict[int, np.ndarray] = {}

    def load_image(i: int) -> np.ndarray:
        if i not in images:
            images[i] = read_rgb(cams[i].image)
        return images[i]

    return load_image


_CACHE: dict = {}


def reduced_texture(path: str, max_side: int = 2048):
    """An original mesh texture decoded at reduced size (JPEG DCT scaling), cached per process."""
    if path not in _CACHE:
        try:
            _CACHE[path] = read_rgb_reduced(path, max_side)
        except (OSError, InputError):  # unreadable, or a texture URL that cannot be staged: no colour from it
            _CACHE[path] = None
        while len(_CACHE) > 4:
            _CACHE.pop(next(iter(_CACHE)))
    return _CACHE[path]


