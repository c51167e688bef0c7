"""The compiled kernels (``ms3d_model.kernels``) against the numpy code they replaced, side by side, on
inputs of a real-density region's size built here.

    .venv/bin/python benchmarks/kernel_bench.py [--points 500000] [--repeat 3]

Each row runs the numpy version (the code as it was before the kernels, kept here as the baseline: the same
inputs, the same outputs) and the function ms3d calls now, checks that both give the same answer, and prints
the best of ``--repeat`` wall times. The k-d tree queries both share are timed inside both, except in the last
row (the candidates come from one query made before).

Inputs: a 5 cm-thinned scan of a wall (noise 3 mm) with a 10 cm-deep window reveal every 1.5 m, ``--points``
points; for the closest points, the pairs of a classify batch (1024 points over a 120-face patch each); for the
point -> mesh candidates, 0.9 M noisy points over 10 cm triangles spanned by the wall's points.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ms3d_model.kernels import closest_point_on_triangles, closest_points_numpy, nearest_of_candidates
from tasks.repair.coarsen import MAX_GAP, flat_points, one_per_voxel
from tasks.repair.fuse import pca_normals, thin_points


def wall(n: int, seed: int = 0) -> np.ndarray:
    """(n, 3) float64: a 5 cm-spaced facade scan (x along, z up, y depth) with recessed windows."""
    rng = np.random.default_rng(seed)
    side = int(np.sqrt(n))
    x, z = np.meshgrid(np.arange(side) * 0.05, np.arange(side) * 0.05)
    x, z = x.ravel(), z.ravel()
    window = ((x % 1.5) > 0.4) & ((x % 1.5) < 1.1) & ((z % 3.0) > 0.9) & ((z % 3.0) < 2.2)
    y = np.where(window, 0.10, 0.0) + rng.normal(scale=0.003, size=len(x))
    return np.c_[x + 500.0, y + 200.0, z + 30.0]


# --------------------------------------------------------------------- the numpy code before the kernels

def pca_normals_numpy(xyz: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    _, idx = cKDTree(xyz).query(xyz, k=k)
    nb = xyz[idx]
    nb -= nb.mean(axis=1, keepdims=True)
    w, v = np.linalg.eigh(np.matmul(nb.transpose(0, 2, 1), nb) / k)
    return v[:, :, 0], w[:, 0] / np.maximum(w.sum(1), 1e-18)


def thin_points_numpy(xyz: np.ndarray, voxel_m: float) -> np.ndarray:
    n = len(xyz)
    cell = np.floor(xyz / voxel_m).astype(np.int64)
    cell -= cell.min(axis=0)
    order = np.argsort((cell[:, 0] << 42) | (cell[:, 1] << 21) | cell[:, 2], kind="stable")
    cs = cell[order]
    new = np.r_[True, (cs[1:] != cs[:-1]).any(axis=1)]
    g_sorted = np.cumsum(new) - 1
    inv = np.empty(n, np.int64)
    inv[order] = g_sorted
    cnt = np.bincount(inv)
    mean = np.stack([np.bincount(inv, xyz[:, c], minlength=len(cnt)) for c in range(3)], axis=1) / cnt[:, None]
    d = np.linalg.norm(xyz - mean[inv], axis=1)[order]
    dmin = np.minimum.reduceat(d, np.flatnonzero(new))
    pos = np.flatnonzero(d == dmin[g_sorted])
    first = np.r_[True, g_sorted[pos][1:] != g_sorted[pos][:-1]]
    return np.sort(order[pos[first]])


def _widest_gap(rel, ok, t1, t2):
    ang = np.arctan2(np.einsum("nkd,nd->nk", rel, t2), np.einsum("nkd,nd->nk", rel, t1))
    m = ok.sum(axis=1)
    ang = np.sort(np.where(ok, ang, 4 * np.pi), axis=1)
    inner = np.diff(ang, axis=1)
    inner[np.arange(inner.shape[1])[None, :] >= (m - 1)[:, None]] = 0.0
    first, last = ang[:, 0], ang[np.arange(len(ang)), np.maximum(m - 1, 0)]
    wrap = np.where(m >= 2, first + 2 * np.pi - last, 2 * np.pi)
    return np.maximum(inner.max(axis=1, initial=0.0), wrap)


def flat_points_numpy(xyz: np.ndarray, coarse_m: float, tolerance_m: float, edges: bool = True) -> np.ndarray:
    n = len(xyz)
    out = np.zeros(n, bool)
    ref = one_per_voxel(xyz, coarse_m / 2)
    tree, k = cKDTree(xyz[ref]), min(32, len(ref))
    local = (xyz - xyz.mean(axis=0)).astype(np.float32)
    local_ref = local[ref]
    for s in range(0, n, 16384):
        d, j = tree.query(xyz[s:s + 16384], k=k, distance_upper_bound=coarse_m)
        ok = np.isfinite(d)
        cnt = np.maximum(ok.sum(axis=1), 1).astype(np.float32)
        w = ok[:, :, None].astype(np.float32)
        rel = local_ref[np.where(ok, j, 0)] - local[s:s + 16384, None, :]
        mean = (rel * w).sum(axis=1) / cnt[:, None]
        nb = (rel - mean[:, None, :]) * w
        lam, vec = np.linalg.eigh(np.matmul(nb.transpose(0, 2, 1), nb) / cnt[:, None, None])
        planar = np.sqrt(np.maximum(lam[:, 0], 0.0)) <= tolerance_m
        inner = _widest_gap(rel, ok & (d > 1e-9), vec[:, :, 2], vec[:, :, 1]) <= MAX_GAP if edges else True
        out[s:s + 16384] = (ok.sum(axis=1) >= 6) & planar & inner
    return out


def closest_numpy(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """The vectorised form the kernel replaced (:func:`ms3d_model.kernels.closest_points_numpy`), on (n, 3, 3)."""
    return closest_points_numpy(p, tri[:, 0], tri[:, 1], tri[:, 2])


def candidates_numpy(p, t, normals, radius, fi, dc):
    """The point -> mesh distances of the cues from their k candidate faces (the code before the kernel)."""
    k = fi.shape[1]
    dist = np.full((len(p), k), np.inf)
    near = closest_numpy(p, t[fi[:, 0]])
    dist[:, 0] = np.linalg.norm(near - p, axis=1)
    valid = fi < len(t)
    valid[:, 0] = False
    row, col = np.nonzero(valid)
    f = fi[row, col]
    bound = dist[:, 0] + 1e-9 * (1.0 + dist[:, 0])
    keep = dc[row, col] - radius[f] <= bound[row]
    row, col, f = row[keep], col[keep], f[keep]
    keep = np.abs(np.einsum("ij,ij->i", p[row] - t[f, 0], normals[f])) <= bound[row]
    row, col, f = row[keep], col[keep], f[keep]
    q = closest_numpy(p[row], t[f])
    dist[row, col] = np.linalg.norm(q - p[row], axis=1)
    rows = np.arange(len(p))
    best = dist.argmin(axis=1)
    d = dist[rows, best]
    fbest = fi[rows, best]
    at = np.full((len(p), k), -1)
    at[row, col] = np.arange(len(row))
    other = best > 0
    near[other] = q[at[other, best[other]]]
    return d, np.sign(((p - near) * normals[fbest]).sum(1)) * d


# --------------------------------------------------------------------- the bench

def best(fn, repeat: int) -> tuple[float, object]:
    out, times = None, []
    for _ in range(repeat):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return min(times), out


def run_cases(cases: list, repeat: int) -> list[dict]:
    """Time each (name, size, numpy fn, ms3d fn, same(numpy out, ms3d out)) case, best of ``repeat``, print
    the side-by-side table and return its rows."""
    print(f"{'kernel':<34}{'input':>20}{'numpy s':>10}{'ms3d s':>10}{'speed-up':>10}  same result")
    rows_out = []
    for name, size, old, new, same in cases:
        t_old, o = best(old, repeat)
        t_new, n = best(new, repeat)
        ok = bool(same(o, n))
        print(f"{name:<34}{size:>20}{t_old:>10.3f}{t_new:>10.3f}{t_old / t_new:>9.1f}x  {ok}")
        rows_out.append({"kernel": name, "numpy_s": t_old, "ms3d_s": t_new, "same": ok})
    return rows_out


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=500_000)
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    xyz = wall(a.points)
    dense = np.concatenate([xyz + np.random.default_rng(i).normal(scale=0.01, size=xyz.shape) for i in range(3)])
    rng = np.random.default_rng(1)
    tri = rng.uniform(0, 2, size=(120 * 900, 3, 3))
    p = rng.uniform(0, 2, size=(1024 * 900, 3))
    rows = rng.integers(0, len(tri), len(p))
    side = int(np.sqrt(len(xyz)))
    r, c = np.meshgrid(np.arange(0, side - 2, 2), np.arange(0, side - 2, 2), indexing="ij")
    a0 = (r * side + c).ravel()
    wall_tri = np.stack([xyz[a0], xyz[a0 + 2], xyz[a0 + 2 * side]], axis=1)  # 10 cm triangles over the wall
    cent = wall_tri.mean(axis=1)
    cross = np.cross(wall_tri[:, 1] - wall_tri[:, 0], wall_tri[:, 2] - wall_tri[:, 0])
    nrm = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-30)
    rad = np.linalg.norm(wall_tri - cent[:, None], axis=2).max(axis=1)
    dc, fi = cKDTree(cent).query(dense[:900_000], k=8)
    pca_normals(xyz[:100], 12), flat_points(xyz[:100], 0.15, 0.015), thin_points(xyz[:100], 0.05)  # compile
    closest_point_on_triangles(p[:4], tri[:4])
    cases = [
        ("PCA normals, k=12", f"{len(xyz):,} points",
         lambda: pca_normals_numpy(xyz, 12), lambda: pca_normals(xyz, 12),
         lambda o, n: np.allclose(np.abs((o[0] * n[0]).sum(1)), 1, atol=1e-9) and np.allclose(o[1], n[1], atol=1e-12)),
        ("plane + edge test (flat_points)", f"{len(xyz):,} points",
         lambda: flat_points_numpy(xyz, 0.15, 0.015), lambda: flat_points(xyz, 0.15, 0.015),
         lambda o, n: (o != n).mean() < 1e-4),
        ("voxel thinning, 5 cm", f"{len(dense):,} points",
         lambda: thin_points_numpy(dense, 0.05), lambda: thin_points(dense, 0.05), np.array_equal),
        ("closest point on triangle", f"{len(p):,} queries",
         lambda: closest_numpy(p, tri[rows]), lambda: closest_point_on_triangles(p, tri[rows]),
         lambda o, n: np.abs(o - n).max() < 1e-9),
        ("point -> mesh from 8 candidates", f"{len(fi):,} queries",
         lambda: candidates_numpy(dense[:900_000], wall_tri, nrm, rad, fi, dc),
         lambda: nearest_of_candidates(dense[:900_000], wall_tri, nrm, rad, fi.astype(np.int64), dc),
         lambda o, n: np.abs(o[0] - n[0]).max() < 1e-12 and np.abs(o[1] - n[1]).max() < 1e-12),
    ]
    return run_cases(cases, a.repeat)

if __name__ == "__main__":
    main()
