"""A hand-made campus for the repair tests (tests/tasks/test_repair_stage.py): one 4 x 4 x 3 m building on a tile corner.

The building stands on the corner (10, 10) of four 10 m tiles. Its mesh is a ring grid: a ground ring
(4 m wide) welded to four walls welded to a roof fan, so every face shares vertex ids with its
neighbours. The mesh walls carry a protrusion band (up to ``bump_m`` outward around z = 1.4 m, all the
way round); the MLS samples the true, flat walls and the ground. Patches whose faces the bump moves
are labelled bad: one region that wraps around the building across all four tiles.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from storage.frame import CampusFrame
from storage.grid import PatchGrid
from storage.patches.schema import TileMeta
from storage.patches.write import write_side_table, write_tile_tables
from storage.workdir.layout import WorkDir, write_campus
from tasks.partition import build_tile_tables

CENTRE = np.array([10.0, 10.0])
HALF = 2.0
HEIGHT = 3.0
TILE_M = 10.0


def _perimeter(step: float) -> tuple[np.ndarray, np.ndarray]:
    """Points every ``step`` around the footprint (counter-clockwise seen from above) and outward normals."""
    c = [CENTRE + HALF * np.array(s) for s in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    pts, nrm = [], []
    n_side = round(2 * HALF / step)
    outward = [np.array([0, -1.0]), np.array([1.0, 0]), np.array([0, 1.0]), np.array([-1.0, 0])]
    for k in range(4):
        a, b = c[k], c[(k + 1) % 4]
        for i in range(n_side):
            t = i / n_side
            pts.append(a + t * (b - a))
            nrm.append(outward[k] + (outward[k - 1] if i == 0 else 0))  # corners: the diagonal
    return np.array(pts), np.array(nrm)


def building_mesh(step: float = 0.25, bump_m: float = 0.15) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertices (n, 3) float64 world, faces (m, 3) int64 outward, bumped (n,) float64 displacement)."""
    p, n = _perimeter(step)
    k = len(p)
    rows = []  # (positions (k, 3), displacement (k,))
    for d in np.arange(4.0, 0.0, -step * 2):  # ground ring, outside in
        rows.append((np.c_[p + d * n, np.zeros(k)], np.zeros(k)))
    for z in np.arange(0.0, HEIGHT + 1e-9, step):
        disp = bump_m * np.exp(-0.5 * ((z - 1.4) / 0.3) ** 2) if bump_m else 0.0
        disp = np.where(np.abs(z - 1.4) < 0.75, disp, 0.0) * np.ones(k)
        rows.append((np.c_[p + disp[:, None] * n / np.linalg.norm(n, axis=1, keepdims=True), np.full(k, z)], disp))
    v = np.concatenate([r[0] for r in rows])
    bumped = np.concatenate([r[1] for r in rows])
    faces = []
    for r in range(len(rows) - 1):
        a = r * k + np.arange(k)
        b = r * k + (np.arange(k) + 1) % k
        c = (r + 1) * k + np.arange(k)
        d = (r + 1) * k + (np.arange(k) + 1) % k
        faces += [np.c_[a, b, d], np.c_[a, d, c]]
    top = (len(rows) - 1) * k + np.arange(k)
    centre = len(v)
    v = np.concatenate([v, [[CENTRE[0], CENTRE[1], HEIGHT]]])
    bumped = np.r_[bumped, 0.0]
    faces.append(np.c_[top, np.roll(top, -1), np.full(k, centre)])
    return v, np.concatenate(faces).astype(np.int64), bumped


def true_mls(spacing: float = 0.04, noise: float = 0.002, seed: int = 0) -> np.ndarray:
    """MLS-like samples of the true flat walls (z in [0.05, 2.9]) and the ground ring: (n, 3) float64."""
    rng = np.random.default_rng(seed)
    p, n = _perimeter(spacing)
    zs = np.arange(0.05, 2.9, spacing)
    walls = np.concatenate([np.c_[p, np.full(len(p), z)] for z in zs])
    ground = np.concatenate([np.c_[p + d * n, np.zeros(len(p))] for d in np.arange(0.1, 3.0, spacing)])
    pts = np.concatenate([walls, ground])
    return pts + rng.normal(0, noise, pts.shape)


def write_campus_workdir(root: Path, step: float = 0.25, bump_m: float = 0.15) -> tuple[WorkDir, np.ndarray]:
    """Write the scene as a v2 work dir (campus.json, one store per tile, labels); returns (wd, bad keys)."""
    wd = WorkDir(root)
    grid = PatchGrid((2.3, 1.0, 0.7), TILE_M)
    frame = CampusFrame(origin=(0.0, 0.0, 0.0), crs="EPSG:32650")
    v, f, bumped = building_mesh(step, bump_m)
    tri = v[f]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    faces = {f"{a}{c}": tri[:, c, i].astype(np.float32) for c in range(3) for i, a in enumerate("xyz")}
    faces |= {f"vid{c}": (7 << 32) + f[:, c] for c in range(3)}
    faces |= {"nx": nrm[:, 0], "ny": nrm[:, 1], "nz": nrm[:, 2], "src_face": np.arange(len(f))}
    pts = true_mls()
    points = {"x": pts[:, 0].astype(np.float32), "y": pts[:, 1].astype(np.float32), "z": pts[:, 2].astype(np.float32),
              "classification": np.full(len(pts), 6, np.uint8)}
    fkey = grid.pack(grid.face_cells([faces[f"{a}{c}"] for c in range(3) for a in "xyz"], frame.origin))
    pkey = grid.keys_local(pts, frame.origin)
    bad = np.unique(fkey[(bumped[f] > 0.02).any(axis=1)])
    ftile, ptile = grid.tile_of_keys(fkey), grid.tile_of_keys(pkey)
    for ix, iy in np.unique(np.concatenate([ftile, ptile]), axis=0).tolist():
        fs = (ftile[:, 0] == ix) & (ftile[:, 1] == iy)
        ps = (ptile[:, 0] == ix) & (ptile[:, 1] == iy)
        p_s, f_s, patches = build_tile_tables({k: c[ps] for k, c in points.items()},
                                              {k: c[fs] for k, c in faces.items()}, grid, frame.origin)
        tile_dir = root / "tiles" / f"{ix}_{iy}"
        meta = TileMeta(tile=f"{ix}_{iy}", patch_size_m=grid.size_m, crs=frame.crs)
        write_tile_tables(tile_dir, p_s, f_s, patches, meta)
        write_side_table(tile_dir, "labels", {"patch": patches["patch"],
                                              "label": np.isin(patches["patch"], bad).astype(np.int8)}, meta)
    cfg_snapshot = {"name": "corner", "work_dir": str(root), "tiling": {"tile_size_m": TILE_M}}
    write_campus(wd, frame, {"matrix": np.eye(4).tolist(), "scale": 1.0}, cfg_snapshot)
    return wd, bad
