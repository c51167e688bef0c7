"""Readers of the texture step's inputs: the vehicle cameras in the campus frame and their images, MLS
occupancy voxels (occluders), and the original mesh textures at reduced size (the colour of faces no image
sees).

The images and ``cameras.json`` are a config input: ``repair.texture.images`` / ``repair.texture.cameras``
(or ``inputs.images`` / ``inputs.cameras`` when the config has them); without either, an ``images``
folder beside the first mesh input is used when it holds a cameras.json (the synth layout).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import numpy as np

from storage.atomic import atomic_path
from storage.errors import InputError
from storage.patch_store import PatchStore
from storage.store_state import store_fingerprint
from tasks.config import CampusConfig


def camera_paths(cfg: CampusConfig) -> tuple[Path | None, Path | None]:
    """(images folder, cameras.json) from ``repair.texture`` (or ``inputs.images`` / ``inputs.cameras``
    when the config has them), else an ``images`` folder beside the first mesh input (synth layout)."""
    tc = cfg.repair.texture
    images = getattr(cfg.inputs, "images", None) or tc.images
    cams = getattr(cfg.inputs, "cameras", None) or tc.cameras
    if images is None and cfg.inputs.mesh:
        guess = Path(cfg.inputs.mesh[0]).parent / "images"
        images = str(guess) if (guess / "cameras.json").exists() else None
    if cams is None and images is not None:
        cams = str(Path(images) / "cameras.json")
    return (Path(images) if images else None), (Path(cams) if cams else None)


def load_cameras(cfg: CampusConfig, doc: dict, frame) -> list:
    """Every camera of cameras.json in the campus frame ([] when there are none).

    cameras.json: {"frame": "MLS" | "mesh", "frame_origin": [x, y, z] world, "cameras": [{"image", "K",
    "R", "t", "width", "height"}]} with X_cam = R (X_world - frame_origin) + t. MLS-frame poses go
    through the campus registration (campus.json), mesh-frame poses only through the origin shift.
    """
    from tasks.repair.texture import cameras_to_frame

    images, path = camera_paths(cfg)
    if path is None or not path.exists():
        return []
    try:
        cj = json.loads(path.read_text())
        entries = cj["cameras"]
        fo = np.asarray(cj.get("frame_origin", [0.0, 0.0, 0.0]), np.float64)
    except (OSError, ValueError, KeyError) as e:
        raise InputError(path, f"not a cameras.json ({e})") from None
    oc = np.asarray(frame.origin, np.float64)
    m = np.eye(4)
    if str(cj.get("frame", "MLS")).lower() == "mls":
        reg = np.asarray(doc["registration"]["matrix"], np.float64)
        m[:3, :3] = reg[:3, :3]
        m[:3, 3] = reg[:3, :3] @ (fo - oc) + reg[:3, 3]
    else:
        m[:3, 3] = fo - oc
    cams = cameras_to_frame(entries, m, str(images or path.parent))
    return [c for c in cams if Path(c.image).is_file()]  # a camera whose image is missing is no candidate


def occupancy(tile_dir: Path, cache: Path, voxel_m: float) -> np.ndarray:
    """(k, 3) float32 centres of a tile's MLS-occupied voxels (``voxel_m`` metres, campus-local), cached in
    ``cache`` (``regions/_occupancy/{tile}.npz``) and rebuilt when the tile's store changes."""
    fp = store_fingerprint(tile_dir)
    if cache.exists():
        with np.load(cache) as z:
            if str(z["fingerprint"]) == fp and float(z["voxel_m"]) == voxel_m:
                return z["centres"]
    store = PatchStore(tile_dir)
    pts, _ = store.read_all(point_columns=["x", "y", "z"], face_columns=["patch"])
    xyz = np.stack([pts["x"], pts["y"], pts["z"]], 1)
    cells = np.unique(np.floor(xyz / voxel_m).astype(np.int64), axis=0)
    centres = ((cells + 0.5) * voxel_m).astype(np.float32)
    with atomic_path(cache) as tmp:
        np.savez(tmp, centres=centres, fingerprint=np.array(fp), voxel_m=np.array(voxel_m))
    return centres


def image_loader(cams: list) -> Callable[[int], np.ndarray]:
    """load_image(i) -> (h, w, 3) uint8 RGB image of ``cams[i]``, each decoded once."""
    images: dict[int, np.ndarray] = {}

    def load_image(i: int) -> np.ndarray:
        if i not in images:
            from PIL import Image

            images[i] = np.asarray(Image.open(cams[i].image).convert("RGB"))
        return images[i]

    return load_image


_CACHE: dict = {}


def reduced_texture(path: str, max_side: int = 2048):
    """An original mesh texture decoded at reduced size (JPEG DCT scaling), cached per process."""
    from PIL import Image

    if path not in _CACHE:
        try:
            im = Image.open(path)
            im.draft("RGB", (max_side, max_side))
            _CACHE[path] = np.asarray(im.convert("RGB"))
        except OSError:
            _CACHE[path] = None
        while len(_CACHE) > 4:
            _CACHE.pop(next(iter(_CACHE)))
    return _CACHE[path]


