"""Synthetic inputs for the benchmarks: MLS-like LAZ strips and gridded meshes over blocks of 100 m, and
sorted staging runs of a single huge tile (for the memory check), all deterministic from a seed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

WORLD_ORIGIN = (589_000.0, 2_712_000.0, 15.0)  # UTM 50N metres, a multiple of 100 m: tiles = blocks
CRS = "EPSG:32650"
BLOCK_M = 100.0  # one synthetic block per default 100 m tile


def _grid(p0, du, dv, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A planar grid of 2*nu*nv triangles spanning p0 + [0, 1] du + [0, 1] dv: (vertices, faces)."""
    s, t = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = np.asarray(p0) + s.reshape(-1, 1) * np.asarray(du) + t.reshape(-1, 1) * np.asarray(dv)
    a = (np.arange(nu)[:, None] * (nv + 1) + np.arange(nv)[None, :]).reshape(-1)
    b, c, d = a + nv + 1, a + 1, a + nv + 2
    return verts, np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])


def _block_buildings(rng: np.random.Generator, x0: float, y0: float) -> np.ndarray:
    """(b, 5) float64 boxes [x, y, width, depth, height] metres inside the block at (x0, y0)."""
    n = int(rng.integers(3, 6))
    w, d, h = rng.uniform(12, 35, n), rng.uniform(10, 25, n), rng.uniform(6, 40, n)
    x = x0 + 5 + rng.uniform(0, 1, n) * (BLOCK_M - 10 - w)
    y = y0 + 5 + rng.uniform(0, 1, n) * (BLOCK_M - 10 - d)
    return np.stack([x, y, w, d, h], 1)


def synthetic_block(seed: int, bx: int, by: int, n_points: int, n_faces: int):
    """Block (bx, by): MLS-like points (65 % on building walls, 35 % on the ground) and a gridded mesh of
    ground, walls and roofs, in campus-local metres; deterministic from (seed, bx, by) alone.

    Returns (xyz (n, 3) float64, attrs dict of (n,) arrays, vertices (v, 3) float64, faces (m, 3) int64).
    """
    rng = np.random.default_rng([seed, bx, by])
    x0, y0 = bx * BLOCK_M, by * BLOCK_M
    b = _block_buildings(rng, x0, y0)
    corners = np.stack([b[:, :2], b[:, :2] + b[:, [2]] * [1, 0], b[:, :2] + b[:, 2:4], b[:, :2] + b[:, [3]] * [0, 1]], 1)
    p0, p1 = corners.reshape(-1, 2), np.roll(corners, -1, axis=1).reshape(-1, 2)
    wall_h = np.repeat(b[:, 4], 4)
    length = np.linalg.norm(p1 - p0, axis=1)
    n_wall = int(n_points * 0.65)
    wall = rng.choice(len(p0), n_wall, p=length * wall_h / (length * wall_h).sum())
    t = rng.random(n_wall)[:, None]
    xy_wall = p0[wall] + t * (p1[wall] - p0[wall]) + rng.normal(0, 0.005, (n_wall, 2))
    xy_ground = [x0, y0] + rng.random((n_points - n_wall, 2)) * (BLOCK_M - 0.01)  # LAS rounding stays inside
    xyz = np.empty((n_points, 3))
    xyz[:n_wall, :2], xyz[:n_wall, 2] = xy_wall, rng.random(n_wall) * wall_h[wall]
    xyz[n_wall:, :2], xyz[n_wall:, 2] = xy_ground, rng.normal(0, 0.01, n_points - n_wall)
    attrs = {"intensity": rng.integers(0, 4096, n_points).astype(np.uint16),
             "gps_time": 302_400.0 + (bx * 64 + by) * 600.0 + np.sort(rng.random(n_points)) * 600.0,
             "rgb": rng.integers(0, 65535, (n_points, 3)).astype(np.uint16),
             "classification": np.where(np.arange(n_points) < n_wall, 6, 2).astype(np.uint8)}
    area = BLOCK_M**2 + (length * wall_h).sum() + (b[:, 2] * b[:, 3]).sum()
    edge = np.sqrt(2 * area / max(n_faces, 1))
    cells = lambda length_m: max(1, round(length_m / edge))
    parts = [_grid([x0, y0, 0], [BLOCK_M, 0, 0], [0, BLOCK_M, 0], cells(BLOCK_M), cells(BLOCK_M))]
    for a, c, h in zip(p0, p1, wall_h):
        parts.append(_grid([*a, 0], [*(c - a), 0], [0, 0, h], cells(np.linalg.norm(c - a)), cells(h)))
    for x, y, w, d, h in b:
        parts.append(_grid([x, y, h], [w, 0, 0], [0, d, 0], cells(w), cells(d)))
    offsets = np.cumsum([0] + [len(v) for v, _ in parts[:-1]])
    verts = np.concatenate([v for v, _ in parts])
    faces = np.concatenate([f + o for (_, f), o in zip(parts, offsets)])
    return xyz, attrs, verts, faces


def write_synthetic_campus(out: Path, blocks: int, points_per_block: int, faces_per_block: int, seed: int) -> Path:
    """A blocks x blocks campus: ``mls/strip_{bx}.laz`` (one per block column) and ``mesh/block_{bx}_{by}.ply``.

    Reused when ``out/inputs.json`` says it was written with the same parameters.
    """
    from storage.formats.meshes import write_ply
    from storage.formats.points import LasChunkWriter, PointChunk

    params = {"blocks": blocks, "points_per_block": points_per_block, "faces_per_block": faces_per_block,
              "seed": seed, "version": 2}
    stamp = out / "inputs.json"
    if stamp.exists() and json.loads(stamp.read_text()) == params:
        return out
    shutil.rmtree(out, ignore_errors=True)
    (out / "mls").mkdir(parents=True)
    (out / "mesh").mkdir()
    origin = np.asarray(WORLD_ORIGIN)
    for bx in range(blocks):
        with LasChunkWriter(out / "mls" / f"strip_{bx:02d}.laz", crs=CRS, offset=origin.round(-3)) as w:
            for by in range(blocks):
                xyz, a, verts, faces = synthetic_block(seed, bx, by, points_per_block, faces_per_block)
                w.write(PointChunk(xyz=xyz + origin, rgb=a["rgb"], intensity=a["intensity"],
                                   gps_time=a["gps_time"], classification=a["classification"]))
                write_ply(out / "mesh" / f"block_{bx:02d}_{by:02d}.ply", verts + origin, faces)
    stamp.write_text(json.dumps(params))
    return out


def synthetic_config(inputs: Path, work: Path):
    from tasks.config import CampusConfig

    return CampusConfig.model_validate({
        "name": inputs.name, "work_dir": str(work),
        "inputs": {"mesh": [str(inputs / "mesh")], "points": [str(inputs / "mls")]},
        "registration": {"mode": "off"}})




def write_big_tile_runs(staging: Path, n_points: int, run_points: int = 2_000_000, seed: int = 0,
                        tile=(5890, 27120)) -> int:
    """Sorted staging runs (as ingest writes them) of one 100 m tile holding ``n_points`` MLS-like points
    (walls and ground of a dense block), ``run_points`` per run; reused when already written. Returns the
    number of runs."""
    from storage.contracts.columns import write_run
    from storage.grid import PatchGrid
    from tasks.partition.kernels import partition_cells

    params = {"n_points": n_points, "run_points": run_points, "seed": seed, "tile": list(tile), "version": 2}
    stamp = staging / "params.json"
    if stamp.exists() and json.loads(stamp.read_text()) == params:
        return len(list(staging.glob("p*.arrow")))
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir(parents=True)
    grid = PatchGrid((2.3, 1.0, 0.7), 100.0)
    origin = np.array([tile[0] * 100.0 - 1000.0, tile[1] * 100.0 - 1000.0, 0.0])
    x0, y0 = tile[0] * 100.0 - origin[0], tile[1] * 100.0 - origin[1]
    runs = 0
    for r, a in enumerate(range(0, n_points, run_points)):
        n = min(run_points, n_points - a)
        xyz, attrs, _, _ = synthetic_block(seed + r, 0, 0, n, 0)
        xyz[:, 0] = np.clip(xyz[:, 0], 1.2, BLOCK_M - 1.2) + x0  # inside the tile: patch centres too
        xyz[:, 1] = np.clip(xyz[:, 1], 0.6, BLOCK_M - 0.6) + y0
        cells = grid.cells_local(xyz, origin)
        order = partition_cells(cells).order
        local = xyz[order].astype(np.float32)
        cols = {"x": local[:, 0], "y": local[:, 1], "z": local[:, 2], "intensity": attrs["intensity"][order],
                "gps_time": attrs["gps_time"][order], "red": attrs["rgb"][order, 0], "green": attrs["rgb"][order, 1],
                "blue": attrs["rgb"][order, 2], "classification": attrs["classification"][order],
                "source": np.full(n, r, np.uint32), "patch": grid.pack(cells[order])}
        write_run(staging / f"p{r:08x}-00000000-00000-000.arrow", cols)
        runs += 1
    stamp.write_text(json.dumps(params))
    (staging / "origin.json").write_text(json.dumps(origin.tolist()))
    return runs
