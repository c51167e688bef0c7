"""Measure a simulated MLS cloud the way real street MLS was measured: wall density, noise, offsets.

The figures the benchmark compares against (real street MLS, 32-channel spinner): wall density p50
~2,500 pts/m^2 within 5 m of the track, ~700 at 5-10 m, ~370 at 10-20 m (the paper's RIEGL system:
~4,000 pts/m^2 at 10 m); flat-wall noise RMS ~5 mm within one rotation, ~11 mm over one pass; wall
offsets between passes 1-5 cm.

Method. Wall points (truth source, FaceClass.WALL) are put on their facade plane (truth faces
grouped by building, normal and plane offset) and binned into square cells in plane coordinates
(horizontal along the wall, vertical up the wall), separately per trajectory (pass):

- density: points per m^2 of each occupied ``cell_m`` cell, p50 per band of horizontal distance
  from the cell centroid to that pass's track;
- noise over one pass: plane fit (PCA) per ``noise_cell_m`` cell and pass, pooled RMS of the
  residuals with 3 degrees of freedom removed per fit; within one rotation: residuals along that
  fitted normal about the mean of each (head, turn) group, 1 dof removed per group;
- pass-to-pass offset: mean signed distance along the truth plane normal per cell and pass;
  differences between every two passes seeing the same ``cell_m`` cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .mls import MlsChunk
from .scene import FaceClass, Mesh
from .trajectory import Trajectory

DEFAULT_BANDS_M = ((0.0, 5.0), (5.0, 10.0), (10.0, 20.0))


def wall_planes(truth: Mesh, offset_quantum_m: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Group WALL faces into facade planes.

    Returns (plane_of_face (m,) int64, -1 for non-wall faces; plane_normal (p, 3) float64 unit,
    outward as the faces are wound). Faces share a plane when building, normal (to 0.01) and plane
    offset (to ``offset_quantum_m``) agree.
    """
    plane_of_face = np.full(truth.n_faces, -1, np.int64)
    wall = np.flatnonzero(truth.face_class == FaceClass.WALL)
    if not len(wall):
        return plane_of_face, np.zeros((0, 3))
    n = truth.face_normals()[wall]
    d = np.sum(n * truth.vertices[truth.faces[wall, 0]], axis=1)
    key = np.column_stack([truth.face_building[wall].astype(np.int64),
                           np.round(n * 100.0).astype(np.int64),
                           np.round(d / offset_quantum_m).astype(np.int64)])
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    plane_of_face[wall] = inv.ravel()
    return plane_of_face, n[first]


def _plane_axes(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(p, 3) unit normals -> (along (p, 3), up (p, 3)) in-plane axes; along is horizontal."""
    along = np.column_stack([-normal[:, 1], normal[:, 0], np.zeros(len(normal))])
    ln = np.linalg.norm(along, axis=1, keepdims=True)
    along = np.where(ln > 1e-9, along / np.maximum(ln, 1e-12), [1.0, 0.0, 0.0])
    return along, np.cross(normal, along)


def _group(*cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer columns (n,) -> (group of each row (n,) int64, rows per group (g,) int64)."""
    _, inv, counts = np.unique(np.column_stack(cols), axis=0, return_inverse=True, return_counts=True)
    return inv.ravel(), counts


def _group_mean(x: np.ndarray, g: np.ndarray, counts: np.ndarray) -> np.ndarray:
    return np.stack([np.bincount(g, x[:, i], len(counts)) for i in range(x.shape[1])], 1) / counts[:, None]


@dataclass
class WallStats:
    """Measured figures (metres, pts/m^2). Arrays per band: density_p50 (b,), density_cells (b,).

    pass_pairs: (q, 2) traj ids; pass_pair_offset_m: (q,) median signed offset (second minus first,
    along the outward wall normal); pass_pair_cells: (q,) cells compared.
    """

    bands_m: tuple
    density_p50: np.ndarray
    density_cells: np.ndarray
    noise_rms_rotation_m: float
    noise_rms_pass_m: float
    pass_offset_median_m: float
    pass_pairs: np.ndarray
    pass_pair_offset_m: np.ndarray
    pass_pair_cells: np.ndarray

    def summary(self) -> str:
        lines = [f"wall density p50 {lo:g}-{hi:g} m: {d:,.0f} pts/m^2 ({c} cells)"
                 for (lo, hi), d, c in zip(self.bands_m, self.density_p50, self.density_cells)]
        lines += [(f"flat-wall noise RMS: {1e3 * self.noise_rms_rotation_m:.1f} mm within one rotation, "
                  f"{1e3 * self.noise_rms_pass_m:.1f} mm over one pass"),
                  (f"pass-to-pass wall offset: median |offset| {1e3 * self.pass_offset_median_m:.1f} mm "
                  f"over {len(self.pass_pairs)} pass pairs")]
        return "\n".join(lines)


def mls_wall_stats(
    cloud: MlsChunk,
    trajectories: list[Trajectory],
    truth: Mesh,
    bands_m: tuple = DEFAULT_BANDS_M,
    cell_m: float = 1.0,
    noise_cell_m: float = 0.5,
    min_points: int = 10,
) -> WallStats:
    """Wall density by range band, flat-wall noise and pass-to-pass offsets of an MLS cloud.

    cloud: the simulated points (``MlsChunk.concat`` of the chunks), mesh frame; trajectories: the
    passes it was scanned from (``traj_id`` indexes them by ``Trajectory.traj_id``); truth: the mesh
    it was scanned from (``cloud.face`` indexes its faces). NaN where nothing could be measured.
    """
    plane_of_face, plane_normal = wall_planes(truth)
    sel = (cloud.source == 0) & (cloud.face_class == FaceClass.WALL)
    sel &= plane_of_face[np.where(sel, cloud.face, 0)] >= 0
    xyz, plane = cloud.xyz[sel], plane_of_face[cloud.face[sel]]
    traj = cloud.traj_id[sel].astype(np.int64)
    along, up = _plane_axes(plane_normal)
    a = np.sum(xyz * along[plane], axis=1)
    b = np.sum(xyz * up[plane], axis=1)

    # density per cell_m cell and pass, banded by distance to that pass's track
    ia, ib = np.floor(a / cell_m).astype(np.int64), np.floor(b / cell_m).astype(np.int64)
    g, counts = _group(traj, plane, ia, ib)
    centre = _group_mean(xyz[:, :2], g, counts)
    cell_traj = np.zeros(len(counts), np.int64)
    cell_traj[g] = traj
    dist = np.full(len(counts), np.inf)
    by_id = {t.traj_id: t for t in trajectories}
    for tid in np.unique(cell_traj):
        m = cell_traj == tid
        _, track, _ = by_id[int(tid)].sample(0.25)
        dist[m] = cKDTree(track[:, :2]).query(centre[m])[0]
    density = counts / cell_m**2
    in_band = [(dist >= lo) & (dist < hi) for lo, hi in bands_m]
    p50 = np.array([np.median(density[m]) if m.any() else np.nan for m in in_band])

    rms_rot, rms_pass = _noise(xyz, traj, plane, a, b, cloud, sel, noise_cell_m, min_points)
    pairs, pair_off, pair_cells, med = _pass_offsets(xyz, plane_normal, plane, traj, ia, ib, min_points)
    return WallStats(tuple(bands_m), p50, np.array([int(m.sum()) for m in in_band]), rms_rot, rms_pass,
                     med, pairs, pair_off, pair_cells)


def _noise(xyz, traj, plane, a, b, cloud, sel, cell, min_points) -> tuple[float, float]:
    """Pooled plane-fit residual RMS (metres) within one rotation and over one pass."""
    ia, ib = np.floor(a / cell).astype(np.int64), np.floor(b / cell).astype(np.int64)
    g, counts = _group(traj, plane, ia, ib)
    ok = counts[g] >= min_points
    if not ok.any():
        return np.nan, np.nan
    g, counts = _group(g[ok])  # renumber the kept groups
    pts = xyz[ok]
    dev = pts - _group_mean(pts, g, counts)[g]
    scatter = np.zeros((len(counts), 3, 3))
    for i in range(3):
        for j in range(i, 3):
            scatter[:, i, j] = scatter[:, j, i] = np.bincount(g, dev[:, i] * dev[:, j], len(counts))
    evals, evecs = np.linalg.eigh(scatter)
    rms_pass = np.sqrt(evals[:, 0].sum() / (counts - 3).sum())
    normal = evecs[:, :, 0]  # (groups, 3), smallest eigenvalue's vector
    head = cloud.scanner_id[sel][ok].astype(np.int64)
    turn = cloud.profile_id[sel][ok].astype(np.int64)
    r, rc = _group(g, head, turn)
    keep = rc[r] >= 3
    if not keep.any():
        return np.nan, float(rms_pass)
    r, rc = _group(r[keep])
    dist = np.sum(pts[keep] * normal[g[keep]], axis=1)
    res = dist - np.bincount(r, dist)[r] / rc[r]
    return float(np.sqrt(np.sum(res**2) / (rc - 1).sum())), float(rms_pass)


def _pass_offsets(xyz, plane_normal, plane, traj, ia, ib, min_points):
    """Per pass pair: median signed offset of cells seen by both passes; overall median |offset|."""
    g, counts = _group(plane, ia, ib, traj)
    ok = counts >= min_points
    dist = np.bincount(g, np.sum(xyz * plane_normal[plane], axis=1), len(counts)) / counts
    rows = np.zeros((len(counts), 4), np.int64)
    rows[g] = np.column_stack([plane, ia, ib, traj])  # np.unique sorted: by cell, then traj
    rows, dist = rows[ok], dist[ok]
    ta, tb, off = [], [], []
    for lag in range(1, len(rows)):
        same = np.all(rows[lag:, :3] == rows[:-lag, :3], axis=1)
        if not same.any():
            break
        i = np.flatnonzero(same)
        ta.append(rows[i, 3])
        tb.append(rows[i + lag, 3])
        off.append(dist[i + lag] - dist[i])
    if not ta:
        return np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0, np.int64), np.nan
    ta, tb, off = np.concatenate(ta), np.concatenate(tb), np.concatenate(off)
    pair, inv, n = np.unique(np.column_stack([ta, tb]), axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    med = np.array([np.median(off[inv == q]) for q in range(len(pair))])
    return pair, med, n, float(np.median(np.abs(off)))
