"""A small hand-made, already co-registered campus in three regions (west, middle, east), each with its
own mesh file and LAS file: the fixture for reprocessing, isolation and bad-input tests (one bad file
must fail only its own region's tiles), and for ``benchmarks/bad_inputs.py``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
import yaml

from storage.formats.meshes import write_obj
from storage.formats.points import PointChunk, write_points

ORIGIN = np.array([500_000.0, 4_000_000.0, 0.0])
REGIONS = {"west": 0.0, "middle": 60.0, "east": 120.0}  # x of each region's first box (metres, local)


def region_mesh(x0: float, subdivisions: int = 2) -> trimesh.Trimesh:
    """Two boxes (buildings) and a ground slab in x in [x0, x0 + 30], y in [0, 30]."""
    parts = [trimesh.creation.box((10, 8, 9), trimesh.transformations.translation_matrix((x0 + 6, 6, 4.5))),
             trimesh.creation.box((8, 10, 6), trimesh.transformations.translation_matrix((x0 + 22, 20, 3))),
             trimesh.creation.box((30, 30, 0.2), trimesh.transformations.translation_matrix((x0 + 15, 15, -0.1)))]
    m = trimesh.util.concatenate(parts)
    for _ in range(subdivisions):
        m = m.subdivide()
    return m


def build_campus(root: Path, tile_size_m: float = 20.0, extra_stray: bool = False, subdivisions: int = 2) -> Path:
    """Write meshes, LAS files and a config into ``root``; returns the config path."""
    (root / "mesh").mkdir(parents=True)
    (root / "mls").mkdir()
    rng = np.random.default_rng(0)
    for name, x0 in REGIONS.items():
        m = region_mesh(x0, subdivisions)
        write_obj(root / "mesh" / f"{name}.obj", np.asarray(m.vertices), np.asarray(m.faces))
        pts, _ = trimesh.sample.sample_surface(m, 20_000, seed=1)
        xyz = pts + rng.normal(0, 0.003, pts.shape) + ORIGIN
        n = len(xyz)
        write_points(root / "mls" / f"{name}.laz", PointChunk(
            xyz=xyz, intensity=rng.integers(0, 60000, n).astype(np.uint16), gps_time=np.sort(rng.uniform(0, 100, n)),
            rgb=rng.integers(0, 65535, (n, 3)).astype(np.uint16), classification=np.full(n, 6, np.uint8)),
            crs="EPSG:32650")
    if extra_stray:  # two far-apart clusters: the tiles between them are in the file's extent but empty
        c = np.concatenate([rng.normal((170, 5, 1), 0.5, (200, 3)), rng.normal((170, 45, 1), 0.5, (200, 3))]) + ORIGIN
        write_points(root / "mls" / "stray.laz", PointChunk(xyz=c, gps_time=np.zeros(len(c))), crs="EPSG:32650")
    cfg = {
        "name": "handmade", "work_dir": "work",
        "inputs": {"mesh": ["mesh"], "points": ["mls"], "crs": "EPSG:32650", "mesh_offset": ORIGIN.tolist()},
        "registration": {"enabled": False},
        "tiling": {"tile_size_m": tile_size_m},
        "cluster": {"n_workers": 2, "tiles_per_task": 3},
    }
    path = root / "campus.yaml"
    path.write_text(yaml.safe_dump(cfg))
    return path


def jittered_parallelogram(origin, u, v, spacing_m: float, rng: np.random.Generator) -> np.ndarray:
    """Points on a jittered grid over the parallelogram ``origin + a u + b v`` (a, b in [0, 1]), about
    ``spacing_m`` apart: (k, 3) float64 metres. A scanned plane for hand-made registration scenes."""
    u, v = np.asarray(u, float), np.asarray(v, float)
    nu, nv = max(int(np.linalg.norm(u) / spacing_m), 1), max(int(np.linalg.norm(v) / spacing_m), 1)
    a, b = np.meshgrid((np.arange(nu) + 0.5) / nu, (np.arange(nv) + 0.5) / nv, indexing="ij")
    a = a.ravel() + rng.uniform(-0.3, 0.3, a.size) / nu
    b = b.ravel() + rng.uniform(-0.3, 0.3, b.size) / nv
    return np.asarray(origin, float) + a[:, None] * u + b[:, None] * v
