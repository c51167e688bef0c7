"""Building blocks of MS3DQE-Net and its baselines: shared MLPs, kernel correlation, neighbour gathers.

Tensors are channels-first as in MeshNet's code: (batch, channels, elements) for per-face / per-point
features; index tensors are (batch, elements, k) int64 into the element axis of the same pair.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class SharedMLP(nn.Sequential):
    """1x1 Conv1d + BatchNorm + ReLU per layer, shared over the elements (PointNet / MeshNet style).

    in_ch -> widths[0] -> ... ; input (B, in_ch, E) (or (B, in_ch, E, k) with ``dims=2``).
    """

    def __init__(self, in_ch: int, widths, dims: int = 1):
        conv, bn = (nn.Conv1d, nn.BatchNorm1d) if dims == 1 else (nn.Conv2d, nn.BatchNorm2d)
        layers = []
        for w in widths:
            layers += [conv(in_ch, w, 1), bn(w), nn.ReLU(inplace=True)]
            in_ch = w
        super().__init__(*layers)
        self.out_ch = in_ch


class DenseMLP(nn.Sequential):
    """Linear + BatchNorm + ReLU (+ Dropout) layers over (B, C) vectors; ``last`` adds a plain Linear."""

    def __init__(self, in_ch: int, widths, last: int | None = None, dropout: float = 0.0):
        layers = []
        for w in widths:
            layers += [nn.Linear(in_ch, w), nn.BatchNorm1d(w), nn.ReLU(inplace=True)]
            if dropout:
                layers.append(nn.Dropout(dropout))
            in_ch = w
        if last is not None:
            layers.append(nn.Linear(in_ch, last))
            in_ch = last
        super().__init__(*layers)
        self.out_ch = in_ch


def gather_neighbours(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Features of neighbours: x (B, C, E), idx (B, E, k) int64 -> (B, C, E, k)."""
    b, c, e = x.shape
    k = idx.shape[2]
    flat = idx.reshape(b, 1, e * k).expand(b, c, e * k)
    return torch.gather(x, 2, flat).reshape(b, c, e, k)


def gather_rows(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows of neighbours: x (B, E, D), idx (B, E, k) -> (B, E, k, D)."""
    b, e, d = x.shape
    k = idx.shape[2]
    return torch.gather(x, 1, idx.reshape(b, e * k, 1).expand(b, e * k, d)).reshape(b, e, k, d)


class NormalKernelCorrelation(nn.Module):
    """MeshNet's face kernel correlation on unit normals (the paper's face-local structure subbranch).

    L kernels of M points on the unit sphere, each point two learnable angles (alpha in (0, pi), beta in
    (0, 2 pi)). Input: a face's normal and its 3 edge neighbours' normals. Response of kernel l =
    mean over the 4 normals and M kernel points of exp(-||n - k||^2 / (2 sigma^2)); ||n - k||^2 = 2 - 2 n.k
    for unit vectors (a matrix product, never a broadcast difference). Output (B, L, F).
    """

    def __init__(self, n_kernels: int = 64, n_points: int = 4, sigma: float = 0.2):
        super().__init__()
        self.sigma = sigma
        self.alpha = nn.Parameter(torch.rand(n_kernels, n_points) * math.pi)
        self.beta = nn.Parameter(torch.rand(n_kernels, n_points) * 2 * math.pi)

    def kernel_points(self) -> torch.Tensor:
        """(L, M, 3) unit vectors."""
        sa = torch.sin(self.alpha)
        return torch.stack([sa * torch.cos(self.beta), sa * torch.sin(self.beta), torch.cos(self.alpha)], dim=-1)

    def forward(self, normals: torch.Tensor, nbr: torch.Tensor) -> torch.Tensor:
        """normals (B, F, 3), nbr (B, F, 3) -> (B, L, F)."""
        sets = torch.cat([normals.unsqueeze(2), gather_rows(normals, nbr)], dim=2)  # (B, F, 4, 3)
        k = self.kernel_points()
        n_k, n_m = k.shape[:2]
        sq_norm = (sets * sets).sum(-1, keepdim=True)  # 1 for unit normals, 0 for a degenerate face
        d2 = sq_norm + 1.0 - 2.0 * sets @ k.reshape(-1, 3).T  # (B, F, 4, L*M)
        r = torch.exp(-d2.clamp_min(0) / (2 * self.sigma ** 2)).reshape(*sets.shape[:3], n_k, n_m)
        return r.mean(dim=(2, 4)).transpose(1, 2).contiguous()


class PointKernelCorrelation(nn.Module):
    """KCNet's kernel correlation of a point with its K neighbours (the face-centre local subbranch).

    L kernels of M free 3-D points (initialised uniform in +-init), compared with the neighbour offsets
    ``x_n - x_i`` (normalised pair units). Response = mean over neighbours and kernel points of
    exp(-||kappa - d||^2 / (2 sigma^2)), via ||d||^2 + ||kappa||^2 - 2 d.kappa. Output (B, L, F).
    """

    def __init__(self, n_kernels: int = 64, n_points: int = 16, sigma: float = 0.05, init: float = 0.2):
        super().__init__()
        self.sigma = sigma
        self.kernels = nn.Parameter((torch.rand(n_kernels, n_points, 3) * 2 - 1) * init)

    def forward(self, xyz: torch.Tensor, knn: torch.Tensor) -> torch.Tensor:
        """xyz (B, F, 3), knn (B, F, K) -> (B, L, F)."""
        d = gather_rows(xyz, knn) - xyz.unsqueeze(2)  # (B, F, K, 3)
        k = self.kernels.reshape(-1, 3)
        d2 = (d * d).sum(-1, keepdim=True) + (k * k).sum(-1) - 2.0 * d @ k.T  # (B, F, K, L*M)
        r = torch.exp(-d2.clamp_min(0) / (2 * self.sigma ** 2))
        r = r.reshape(*d.shape[:3], *self.kernels.shape[:2])
        return r.mean(dim=(2, 4)).transpose(1, 2).contiguous()


def response_stats(r: torch.Tensor) -> dict:
    """Summary of kernel-correlation responses: mean, median, fraction above 1e-3 and 0.1."""
    r = r.detach().float().reshape(-1)
    return {"mean": float(r.mean()), "median": float(r.median()), "frac_gt_1e-3": float((r > 1e-3).float().mean()),
            "frac_gt_0.1": float((r > 0.1).float().mean())}


def point_mesh_geometry(points: torch.Tensor, centres: torch.Tensor, normals: torch.Tensor,
                        scale: torch.Tensor) -> torch.Tensor:
    """Per-point geometry against the mesh, in metres: for each point its nearest face (by centre), the
    signed distance to that face's plane along its normal and the distance to its centre, squashed
    as tanh(d / 0.15 m) and tanh(d / 0.5 m) so that a 5 cm offset and a 2 m gap both register.

    points (B, N, 3), centres / normals (B, F, 3) in the pair's normalised frame; scale (B,) metres per
    unit. Returns (B, N, 2) float32.

    >>> p = torch.tensor([[[0.0, 0.0, 0.1]]]); c = torch.zeros(1, 1, 3); n = torch.tensor([[[0.0, 0.0, 1.0]]])
    >>> g = point_mesh_geometry(p, c, n, torch.tensor([1.5]))
    >>> [round(float(v), 3) for v in g[0, 0]]  # 0.15 m in front of the face: tanh(1), tanh(0.3)
    [0.762, 0.291]
    """
    d = torch.cdist(points, centres)  # (B, N, F)
    near = d.argmin(dim=2)  # (B, N)
    idx = near.unsqueeze(2).expand(-1, -1, 3)
    c, n = torch.gather(centres, 1, idx), torch.gather(normals, 1, idx)  # (B, N, 3)
    s = scale.view(-1, 1)
    signed = ((points - c) * n).sum(dim=2) * s
    to_centre = d.gather(2, near.unsqueeze(2))[:, :, 0] * s
    return torch.stack([torch.tanh(signed / 0.15), torch.tanh(to_centre / 0.5)], dim=2)
