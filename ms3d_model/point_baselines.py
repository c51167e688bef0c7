"""The paper's point-cloud baselines of Table 3 besides PointNet: PointNet++ (single-scale grouping) and a
PointCNN-style network of X-convolutions. Points only, as in the paper's table.

Input: ``batch["points"]`` (B, N, 3) float32, the pair's MLS points in its normalised frame (within
[-1, 1], :func:`ms3d_model.features.normalise_pair`). Output: (B, 2) logits (0 good, 1 bad).

- **PointNet++** (Qi et al., NeurIPS 2017), SSG: two set-abstraction levels (farthest point sampling of
  the centres, ball query of the neighbours, a shared MLP on [offset / radius, feature], max over the
  neighbours), then a global abstraction (shared MLP, max over all centres) and an MLP head. Widths are the
  published classification network's divided by 2-4 for a 2-core CPU (``pointnet2_*`` fields of
  :class:`~ms3d_model.net.NetConfig`); the radii are in normalised pair units.
- **PointCNN** (Li et al., NeurIPS 2018): X-convolution layers. For P representative points (farthest point
  sampling) and their K nearest neighbours (every D-th of the K x D nearest: dilation), the neighbours'
  local offsets are lifted by an MLP to C_delta features and concatenated with their input features; an MLP
  of the K x 3 offsets predicts the K x K X-transform, which weights and permutes the neighbours; a
  depthwise-separable convolution over the K transformed neighbours gives the output feature. Three layers,
  global mean over the last representatives, MLP head.

Both take each point's position in the pair frame as its input feature beside the local offsets (ours: the
published classifiers group local offsets only, which makes them blind to where the points lie in the pair's
frame, i.e. relative to the mesh they are graded against; measured on a toy of points lifted off a flat mesh,
PointCNN without it stayed at chance after 15 epochs).

Sampling and grouping are plain torch on the input's device (no compiled extension), batched over pairs.
"""

from __future__ import annotations

import torch
from torch import nn

from .layers import DenseMLP, SharedMLP


def farthest_points(xyz: torch.Tensor, m: int) -> torch.Tensor:
    """(B, m) int64 indices of ``m`` farthest points of xyz (B, N, 3), starting at each pair's point 0
    (deterministic). m >= N returns every index."""
    b, n, _ = xyz.shape
    if m >= n:
        return torch.arange(n, device=xyz.device).expand(b, n).clone()
    out = torch.zeros(b, m, dtype=torch.int64, device=xyz.device)
    dist = torch.full((b, n), float("inf"), device=xyz.device)
    rows = torch.arange(b, device=xyz.device)
    far = torch.zeros(b, dtype=torch.int64, device=xyz.device)
    for i in range(m):
        out[:, i] = far
        d = ((xyz - xyz[rows, far].unsqueeze(1)) ** 2).sum(-1)
        dist = torch.minimum(dist, d)
        far = dist.argmax(dim=1)
    return out


def gather_points(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Rows of x (B, N, C) at idx (B, ...) int64 -> (B, ..., C)."""
    b = x.shape[0]
    flat = idx.reshape(b, -1)
    out = torch.gather(x, 1, flat.unsqueeze(-1).expand(-1, -1, x.shape[-1]))
    return out.reshape(*idx.shape, x.shape[-1])


def ball_query(xyz: torch.Tensor, centres: torch.Tensor, radius: float, k: int) -> torch.Tensor:
    """(B, m, k) int64: for each centre (B, m, 3), up to k of the points (B, N, 3) within ``radius``, nearest
    first; short rows repeat their nearest (a centre is one of the points, so it has at least itself)."""
    d2 = torch.cdist(centres, xyz) ** 2  # (B, m, N)
    k = min(k, xyz.shape[1])
    near_d, near_i = torch.topk(d2, k, dim=2, largest=False)
    outside = near_d > radius * radius
    return torch.where(outside, near_i[:, :, :1].expand_as(near_i), near_i)


class SetAbstraction(nn.Module):
    """One PointNet++ level: m centres, k neighbours within ``radius``, shared MLP on [offset / radius,
    features], max over the neighbours. xyz (B, N, 3), feats (B, N, C) or None -> (centres (B, m, 3),
    features (B, m, C'))."""

    def __init__(self, m: int, radius: float, k: int, in_ch: int, widths):
        super().__init__()
        self.m, self.radius, self.k = m, radius, k
        self.mlp = SharedMLP(3 + in_ch, widths, dims=2)

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        centres = gather_points(xyz, farthest_points(xyz, self.m))
        nbr = ball_query(xyz, centres, self.radius, self.k)  # (B, m, k)
        local = (gather_points(xyz, nbr) - centres.unsqueeze(2)) / self.radius  # (B, m, k, 3)
        z = local if feats is None else torch.cat([local, gather_points(feats, nbr)], dim=-1)
        z = self.mlp(z.permute(0, 3, 1, 2))  # (B, C', m, k)
        return centres, z.max(dim=3).values.transpose(1, 2).contiguous()


class PointNet2(nn.Module):
    """PointNet++ SSG classifier (module docstring); configured by the ``pointnet2_*`` fields of NetConfig."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg
        (m1, r1, k1), (m2, r2, k2) = cfg.pointnet2_levels
        w1, w2, w3 = cfg.pointnet2_mlps
        self.sa1 = SetAbstraction(m1, r1, k1, 3, w1)
        self.sa2 = SetAbstraction(m2, r2, k2, w1[-1], w2)
        self.glob = SharedMLP(3 + w2[-1], w3)
        self.head = DenseMLP(w3[-1], cfg.head, last=2, dropout=cfg.dropout)

    def forward(self, batch: dict[str, torch.Tensor], log_kc: bool = False) -> torch.Tensor:
        xyz = batch["points"]
        c1, f1 = self.sa1(xyz, xyz)
        c2, f2 = self.sa2(c1, f1)
        g = self.glob(torch.cat([c2, f2], dim=-1).transpose(1, 2)).max(dim=2).values
        return self.head(g)


def knn(xyz: torch.Tensor, centres: torch.Tensor, k: int) -> torch.Tensor:
    """(B, m, k) int64 the k nearest points (B, N, 3) of each centre (B, m, 3), nearest first."""
    return torch.topk(torch.cdist(centres, xyz), min(k, xyz.shape[1]), dim=2, largest=False).indices


class XConv(nn.Module):
    """One X-convolution (PointCNN): P representatives, K neighbours at dilation D, C_delta lifted offset
    features, output C. xyz (B, N, 3), feats (B, N, C_in) or None -> (reps (B, P, 3), features (B, P, C))."""

    def __init__(self, p: int, k: int, dilation: int, in_ch: int, c_delta: int, out_ch: int):
        super().__init__()
        self.p, self.k, self.d = p, k, dilation
        self.lift = nn.Sequential(nn.Linear(3, c_delta), nn.ELU(), nn.Linear(c_delta, c_delta), nn.ELU())
        self.x_mlp = nn.Sequential(nn.Linear(3 * k, k * k), nn.ELU(), nn.Linear(k * k, k * k), nn.ELU(),
                                   nn.Linear(k * k, k * k))
        c = c_delta + in_ch
        mult = max(1, out_ch // c)
        self.depthwise = nn.Conv2d(c, c * mult, (1, k), groups=c)  # over the K transformed neighbours
        self.pointwise = nn.Conv1d(c * mult, out_ch, 1)
        self.bn = nn.BatchNorm1d(out_ch)

    def forward(self, xyz: torch.Tensor, feats: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        b = xyz.shape[0]
        reps = gather_points(xyz, farthest_points(xyz, self.p))
        kd = min(self.k * self.d, xyz.shape[1])
        nbr = knn(xyz, reps, kd)[:, :, ::self.d][:, :, :self.k]  # (B, P, K)
        k = nbr.shape[2]
        local = gather_points(xyz, nbr) - reps.unsqueeze(2)  # (B, P, K, 3)
        f = self.lift(local)
        if feats is not None:
            f = torch.cat([f, gather_points(feats, nbr)], dim=-1)  # (B, P, K, C)
        if k < self.k:  # fewer points than K: pad with the nearest
            pad = self.k - k
            local = torch.cat([local, local[:, :, :1].expand(-1, -1, pad, -1)], dim=2)
            f = torch.cat([f, f[:, :, :1].expand(-1, -1, pad, -1)], dim=2)
        x = self.x_mlp(local.reshape(b, reps.shape[1], -1)).reshape(b, reps.shape[1], self.k, self.k)
        fx = x @ f  # (B, P, K, C): the neighbours weighted and permuted
        z = self.depthwise(fx.permute(0, 3, 1, 2)).squeeze(3)  # (B, C * mult, P)
        return reps, torch.relu(self.bn(self.pointwise(z))).transpose(1, 2).contiguous()


class PointCNN(nn.Module):
    """PointCNN-style classifier of X-convolutions (module docstring); the ``pointcnn_layers`` field of
    NetConfig: (P, K, D, C_delta, C) per layer."""

    def __init__(self, cfg):
        super().__init__()
        self.cfg = cfg
        layers, in_ch = [], 3
        for p, k, d, c_delta, c in cfg.pointcnn_layers:
            layers.append(XConv(p, k, d, in_ch, c_delta, c))
            in_ch = c
        self.layers = nn.ModuleList(layers)
        self.head = DenseMLP(in_ch, cfg.head, last=2, dropout=cfg.dropout)

    def forward(self, batch: dict[str, torch.Tensor], log_kc: bool = False) -> torch.Tensor:
        xyz = batch["points"]
        feats = xyz
        for layer in self.layers:
            xyz, feats = layer(xyz, feats)
        return self.head(feats.mean(dim=1))


__all__ = ["PointCNN", "PointNet2", "SetAbstraction", "XConv", "ball_query", "farthest_points", "gather_points",
           "knn"]
