"""MS3DQE-Net (Liu et al. 2023, §4.3) and the networks it is compared with, as configurations of one class.

Input: a batch dict of tensors (see :mod:`ms3d_model.features` for the conventions)::

    points     (B, N, 3) float32   MLS points, normalised pair frame
    centres    (B, F, 3) float32   face centres          normals (B, F, 3) unit face normals
    corners    (B, F, 18) float32  two edge vectors per corner, corners 0, 1, 2
    face_nbr   (B, F, 3) int64     edge neighbours (self on a boundary)
    centre_knn (B, F, K) int64     K nearest face centres
    cues       (B, C) float32      hand-made pair cues (MS3DQE-Net+ only, ``n_cues > 0``)
    scale, n_points, n_faces (B,) float32  metres per unit, raw counts (``geometry`` only)

Output: (B, 2) logits (0 good, 1 bad).

Modules and their switches (Table 4's rows; every ablation is a :class:`NetConfig`):

- ``points``  point branch: shared MLP(32, 64) + max pool -> Fea_point (64).
- ``face``    face feature subbranch: face-shape (MLP(32, 32) per corner, averaged, MLP(64, 64)), the
  face-local structure (kernel correlation of the face's and its 3 edge neighbours' normals), and the raw
  normal, concatenated (64 + 64 + 3 = 131) and fed to an MLP -> Fea_face (131).
- ``centre_global`` face-centre global subbranch: MLP(64, 64) per face centre; its "pooling" is the final
  max pool of the mesh features built on it (MeshNet's spatial descriptor).
- ``centre_local`` face-centre local subbranch: kernel correlation of each centre with its K nearest
  centres, an MLP(64) and a max pool -> Fea_center_local (64).
- ``kernel_correlation`` both kernel-correlation layers; off, each is replaced by a shared MLP over the
  neighbour differences (normals n_j - n_i with n_i; centre offsets) + max over the neighbours, same width.
- ``point_aggregation``: [Fea_point, Fea_center_local] -> MLP(128, 256) -> 64 = Fea_point_deeper; off, the
  two vectors are passed on as they are.
- Mesh aggregation (always on when a mesh feature exists), MeshNet's two "mesh convolutions": combination
  MLP([centre, face]) -> Fea_center_deeper0 (256) / 1 (512) and neighbour aggregation (concat a face's
  feature with each edge neighbour's, MLP, max over the 3 neighbours, MLP) -> Fea_face_deeper0 / 1;
  [center_deeper1, face_deeper1] -> MLP -> 1024 per face; Fea_mesh = max over faces of
  [1024, center_deeper0, center_deeper1].
- ``geometry`` (ours, off in the paper's configurations): what the grading needs, fed early. Each point
  enters the point branch with its signed distance to its nearest face's plane and its distance to that
  face's centre, in metres (:func:`~ms3d_model.layers.point_mesh_geometry`; the paper's net compares
  points and mesh only after global pooling, in a frame rescaled per pair), and the fusion gets the
  pair's metric scale and its point and face counts (log).
- Fusion: [Fea_mesh, Fea_point_deeper (, cue MLP)] -> 1024 (Fea_fusion) -> MLP(512, 256, 2), dropout 0.5.

Choices where the paper is open (each configurable): the corner convention (``corners``: "edges" = the
paper's two edge vectors per corner, "meshnet" = MeshNet's centre-to-vertex vectors in pairs); the global
pool happens once, on the mesh features, and the fusion MLP acts on pooled vectors (MeshNet applies its
1792 -> 1024 MLP per face before pooling: the same parameters, F times the work); K = 3 centre neighbours
(Table 2 gives I_neighbor_center dimension 3).

Kernel-correlation scale: the paper's sigma = 0.005 (from KCNet) leaves the layer dead on our inputs (see
:func:`kernel_response_stats` and the model card: on unit normals nearly every response is 0, on centre
offsets of ~0.05-0.1 units too). We keep sigma as a config field and set it by measurement:
``sigma_normal`` = 0.2 (MeshNet's value on unit normals) and ``sigma_centre`` = 0.05 in normalised pair units,
where the responses are spread over (0, 1).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
from torch import nn

from .layers import (
    DenseMLP,
    NormalKernelCorrelation,
    PointKernelCorrelation,
    SharedMLP,
    gather_neighbours,
    gather_rows,
    point_mesh_geometry,
    response_stats,
)
from .point_baselines import PointCNN, PointNet2

PAPER_PARAMETERS = 4_541_057


@dataclass(frozen=True)
class NetConfig:
    """Architecture of a network (defaults: the paper's MS3DQE-Net widths)."""

    arch: str = "ms3dqe"  # "ms3dqe" (MS3DQE-Net, its ablations, MeshNet-style, MS3DQE-Net+) | "pointnet" |
    #                       "pointnet2" | "pointcnn" (ms3d_model.point_baselines) | "gbm"
    points: bool = True
    face: bool = True
    centre_global: bool = True
    centre_local: bool = True
    kernel_correlation: bool = True
    point_aggregation: bool = True
    n_cues: int = 0  # > 0: MS3DQE-Net+ (hand-made pair cues join the fusion feature)
    geometry: bool = False  # per-point distances to the mesh in metres + the pair's scale and counts (ours)
    corners: str = "edges"  # "edges" (paper) | "meshnet"
    point_mlp: tuple[int, ...] = (32, 64)
    corner_mlp: tuple[int, ...] = (32, 32)
    shape_mlp: tuple[int, ...] = (64, 64)
    face_dim: int = 131
    centre_mlp: tuple[int, ...] = (64, 64)
    kc_kernels: int = 64
    kc_normal_points: int = 4
    kc_centre_points: int = 16
    sigma_normal: float = 0.2
    sigma_centre: float = 0.05
    centre_local_dim: int = 64
    point_agg: tuple[int, ...] = (128, 256)
    point_dim: int = 64
    mesh_dims: tuple[int, int] = (256, 512)
    mesh_fusion: int = 1024
    fusion_dim: int = 1024
    head: tuple[int, ...] = (512, 256)
    dropout: float = 0.5
    cue_dim: int = 64
    pointnet_mlp: tuple[int, ...] = (64, 64, 64, 128, 1024)
    tree_depth: int = 0  # arch "gbm": levels walked by TreeNet
    # PointNet++ SSG: (centres, radius in pair units, neighbours) per level; shared MLP widths of the two levels
    # and of the global abstraction (the published classifier's / 2-4)
    pointnet2_levels: tuple = ((64, 0.25, 16), (16, 0.5, 16))
    pointnet2_mlps: tuple = ((32, 32, 64), (64, 64, 128), (128, 256))
    # PointCNN: (representatives P, neighbours K, dilation D, lifted offset features C_delta, output C) per layer
    pointcnn_layers: tuple = ((128, 8, 1, 16, 32), (64, 8, 2, 16, 64), (16, 8, 2, 16, 128))

    def __post_init__(self):
        if self.arch not in ("ms3dqe", "pointnet", "pointnet2", "pointcnn", "gbm"):
            raise ValueError(f"unknown arch {self.arch!r}")
        if self.arch == "ms3dqe" and not (self.face or self.centre_global):
            raise ValueError("MS3DQE-Net needs the face or the face-centre global subbranch (a mesh feature)")
        if self.corners not in ("edges", "meshnet"):
            raise ValueError(f"unknown corner convention {self.corners!r}")

    def to_json(self) -> dict:
        return asdict(self)

    @classmethod
    def from_json(cls, d: dict) -> NetConfig:
        def tup(v):
            return tuple(tup(x) for x in v) if isinstance(v, (list, tuple)) else v

        return cls(**{k: tup(v) for k, v in d.items()})


# Table 4's ablations (1)-(6) and the full network, as switch settings.
ABLATIONS: dict[str, dict] = {
    "(1)": {"points": False, "centre_local": False, "point_aggregation": False},
    "(2)": {"centre_global": False},
    "(3)": {"face": False},
    "(4)": {"kernel_correlation": False},
    "(5)": {"point_aggregation": False},
    "(6)": {"centre_local": False},
    "Full": {},
}
MESHNET = {"points": False, "centre_local": False, "point_aggregation": False, "corners": "meshnet"}


def meshnet_corners(corners: torch.Tensor) -> torch.Tensor:
    """MeshNet's face-rotate input from ours: (B, F, 18) edge corners -> (B, F, 18) = pairs (c1, c2), (c2, c3),
    (c3, c1) of the centre-to-vertex vectors c_i = v_i - centre."""
    e01, e02 = corners[..., 0:3], corners[..., 3:6]
    c0 = -(e01 + e02) / 3.0
    c1, c2 = c0 + e01, c0 + e02
    return torch.cat([c0, c1, c1, c2, c2, c0], dim=-1)


class NeighbourMLP(nn.Module):
    """Stand-in for a kernel-correlation layer when it is switched off: MLP over [own, neighbour - own]
    for each neighbour, max over the neighbours. x (B, E, D) rows, idx (B, E, k) -> (B, out, E)."""

    def __init__(self, d: int, out: int):
        super().__init__()
        self.mlp = SharedMLP(2 * d, (out,), dims=2)

    def forward(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        nb = gather_rows(x, idx)  # (B, E, k, D)
        own = x.unsqueeze(2).expand_as(nb)
        z = torch.cat([own, nb - own], dim=-1).permute(0, 3, 1, 2)  # (B, 2D, E, k)
        return self.mlp(z).max(dim=3).values


class NeighbourAggregation(nn.Module):
    """MeshNet's aggregation: concat a face's feature with each edge neighbour's, MLP, max over the 3
    neighbours, MLP to ``out``. x (B, C, F), nbr (B, F, 3) -> (B, out, F).

    The first layer's weight on the concatenation [x_i, x_j] is split as W_own x_i + W_nbr x_j, both
    computed once per face and gathered, which is the same function at a third of the work.
    """

    def __init__(self, c: int, out: int):
        super().__init__()
        self.own = nn.Conv1d(c, c, 1)
        self.nbr = nn.Conv1d(c, c, 1, bias=False)
        self.bn = nn.BatchNorm2d(c)
        self.out = SharedMLP(c, (out,))

    def forward(self, x: torch.Tensor, nbr: torch.Tensor) -> torch.Tensor:
        z = self.own(x).unsqueeze(3) + gather_neighbours(self.nbr(x), nbr)  # (B, C, F, 3)
        return self.out(torch.relu(self.bn(z)).max(dim=3).values)


class MS3DQENet(nn.Module):
    """MS3DQE-Net with a switch per module (see the module docstring); also MeshNet-style and MS3DQE-Net+."""

    def __init__(self, cfg: NetConfig = NetConfig()):
        super().__init__()
        self.cfg = c = cfg
        if c.points:
            self.point_mlp = SharedMLP(5 if c.geometry else 3, c.point_mlp)
        if c.face:
            self.corner_mlp = SharedMLP(6, c.corner_mlp, dims=2)
            self.shape_mlp = SharedMLP(c.corner_mlp[-1], c.shape_mlp)
            self.normal_kc = (NormalKernelCorrelation(c.kc_kernels, c.kc_normal_points, c.sigma_normal)
                              if c.kernel_correlation else NeighbourMLP(3, c.kc_kernels))
            self.face_mlp = SharedMLP(c.shape_mlp[-1] + c.kc_kernels + 3, (c.face_dim,))
        if c.centre_global:
            self.centre_mlp = SharedMLP(3, c.centre_mlp)
        if c.centre_local:
            self.centre_kc = (PointKernelCorrelation(c.kc_kernels, c.kc_centre_points, c.sigma_centre)
                              if c.kernel_correlation else NeighbourMLP(3, c.kc_kernels))
            self.centre_local_mlp = SharedMLP(c.kc_kernels, (c.centre_local_dim,))
        comb_in = (c.centre_mlp[-1] if c.centre_global else 0) + (c.face_dim if c.face else 0)
        agg_in = c.face_dim if c.face else c.centre_mlp[-1]
        d0, d1 = c.mesh_dims
        self.comb0, self.agg0 = SharedMLP(comb_in, (d0,)), NeighbourAggregation(agg_in, d0)
        self.comb1, self.agg1 = SharedMLP(2 * d0, (d1,)), NeighbourAggregation(d0, d1)
        self.mesh_fusion = SharedMLP(2 * d1, (c.mesh_fusion,))
        point_vec = (c.point_mlp[-1] if c.points else 0) + (c.centre_local_dim if c.centre_local else 0)
        if c.point_aggregation and point_vec:
            self.point_agg = DenseMLP(point_vec, c.point_agg, last=c.point_dim)
            point_vec = c.point_dim
        fused_in = c.mesh_fusion + d0 + d1 + point_vec + (3 if c.geometry else 0)
        if c.n_cues:
            self.register_buffer("cue_mean", torch.zeros(c.n_cues))
            self.register_buffer("cue_std", torch.ones(c.n_cues))
            self.cue_mlp = DenseMLP(c.n_cues, (c.cue_dim, c.cue_dim))
            fused_in += c.cue_dim
        self.fusion = DenseMLP(fused_in, (c.fusion_dim,))
        self.head = DenseMLP(c.fusion_dim, c.head, last=2, dropout=c.dropout)
        self._kc_log: dict[str, torch.Tensor] = {}

    def forward(self, batch: dict[str, torch.Tensor], log_kc: bool = False) -> torch.Tensor:
        c = self.cfg
        centres, normals, nbr = batch["centres"], batch["normals"], batch["face_nbr"]
        pooled = []
        per_face = []
        if c.face:
            corners = batch["corners"] if c.corners == "edges" else meshnet_corners(batch["corners"])
            b, f, _ = corners.shape
            z = corners.reshape(b, f, 3, 6).permute(0, 3, 1, 2)  # (B, 6, F, 3 corners)
            shape = self.shape_mlp(self.corner_mlp(z).mean(dim=3))
            structure = self.normal_kc(normals, nbr)
            if log_kc and c.kernel_correlation:
                self._kc_log["normal"] = structure
            face = self.face_mlp(torch.cat([shape, structure, normals.transpose(1, 2)], dim=1))
        if c.centre_global:
            centre = self.centre_mlp(centres.transpose(1, 2))
            per_face.append(centre)
        if c.face:
            per_face.append(face)
        agg_in = face if c.face else centre
        cd0 = self.comb0(torch.cat(per_face, dim=1))
        fd0 = self.agg0(agg_in, nbr)
        cd1 = self.comb1(torch.cat([cd0, fd0], dim=1))
        fd1 = self.agg1(fd0, nbr)
        fused = self.mesh_fusion(torch.cat([cd1, fd1], dim=1))
        mesh_vec = torch.cat([fused, cd0, cd1], dim=1).max(dim=2).values
        if c.points:
            pts = batch["points"]
            if c.geometry:
                pts = torch.cat([pts, point_mesh_geometry(pts, centres, normals, batch["scale"])], dim=2)
            pooled.append(self.point_mlp(pts.transpose(1, 2)).max(dim=2).values)
        if c.centre_local:
            r = self.centre_kc(centres, batch["centre_knn"])
            if log_kc and c.kernel_correlation:
                self._kc_log["centre"] = r
            pooled.append(self.centre_local_mlp(r).max(dim=2).values)
        parts = [mesh_vec]
        if pooled:
            pv = torch.cat(pooled, dim=1)
            parts.append(self.point_agg(pv) if hasattr(self, "point_agg") else pv)
        if c.geometry:
            parts.append(torch.stack([torch.log(batch["scale"]), torch.log1p(batch["n_points"]) / 8,
                                      torch.log1p(batch["n_faces"]) / 8], dim=1))
        if c.n_cues:
            parts.append(self.cue_mlp((batch["cues"][:, :c.n_cues] - self.cue_mean) / self.cue_std))  # older cue sets lead
        return self.head(self.fusion(torch.cat(parts, dim=1)))


class PointNet(nn.Module):
    """PointNet baseline (points only): shared MLP(64, 64, 64, 128, 1024), max pool, MLP(512, 256, 2).
    Without the T-Nets (the paper's 3,528,790 parameters include them); the patches are already normalised."""

    def __init__(self, cfg: NetConfig):
        super().__init__()
        self.cfg = cfg
        self.mlp = SharedMLP(3, cfg.pointnet_mlp)
        self.head = DenseMLP(cfg.pointnet_mlp[-1], cfg.head, last=2, dropout=cfg.dropout)

    def forward(self, batch: dict[str, torch.Tensor], log_kc: bool = False) -> torch.Tensor:
        return self.head(self.mlp(batch["points"].transpose(1, 2)).max(dim=2).values)


def build_net(cfg: NetConfig, state_dict: dict | None = None) -> nn.Module:
    """The network of a config (a TreeNet takes its array shapes from ``state_dict``)."""
    if cfg.arch == "gbm":
        return TreeNet(cfg, None if state_dict is None else {k: v.cpu().numpy() for k, v in state_dict.items()})
    return {"pointnet": PointNet, "pointnet2": PointNet2, "pointcnn": PointCNN}.get(cfg.arch, MS3DQENet)(cfg)


def n_parameters(net: nn.Module) -> int:
    return sum(p.numel() for p in net.parameters())


def kernel_response_stats(net: nn.Module, batch: dict[str, torch.Tensor], sigmas=(0.005, None)) -> dict:
    """Statistics of both kernel-correlation layers' responses on ``batch`` at the paper's sigma (0.005) and
    at the configured one (None): {"normal@0.005": {...}, "centre@0.05": {...}, ...}."""
    out = {}
    if not isinstance(net, MS3DQENet) or not net.cfg.kernel_correlation:
        return out
    with torch.no_grad():
        for layer_name, attr in (("normal", "normal_kc"), ("centre", "centre_kc")):
            layer = getattr(net, attr, None)
            if layer is None:
                continue
            saved = layer.sigma
            for s in sigmas:
                layer.sigma = saved if s is None else s
                r = (layer(batch["normals"], batch["face_nbr"]) if layer_name == "normal"
                     else layer(batch["centres"], batch["centre_knn"]))
                out[f"{layer_name}@{layer.sigma:g}"] = response_stats(r)
            layer.sigma = saved
    return out


def with_switches(cfg: NetConfig, **switches) -> NetConfig:
    return replace(cfg, **switches)


__all__ = ["ABLATIONS", "MESHNET", "PAPER_PARAMETERS", "MS3DQENet", "NetConfig", "PointNet", "build_net",
           "kernel_response_stats", "n_parameters", "with_switches"]


class TreeNet(nn.Module):
    """The gradient-boosting baseline as a module, so it ships and loads like the networks (a state dict of
    tensors, ``weights_only=True``). Input: ``batch["cues"]`` (B, C); output (B, 2) logits [0, raw score],
    so softmax gives the trees' probability of "bad". Trees are walked level by level, all at once."""

    def __init__(self, cfg: NetConfig, arrays: dict | None = None):
        super().__init__()
        self.cfg = cfg
        a = arrays or {"feature": np.zeros((1, 1), np.int64), "threshold": np.zeros((1, 1), np.float32),
                       "missing_left": np.zeros((1, 1), bool), "is_leaf": np.ones((1, 1), bool),
                       "left": np.zeros((1, 1), np.int64), "right": np.zeros((1, 1), np.int64),
                       "value": np.zeros((1, 1), np.float32), "baseline": np.zeros(1, np.float32)}
        for k, v in a.items():
            self.register_buffer(k, torch.from_numpy(np.ascontiguousarray(v)))
        self.depth = cfg.tree_depth

    def forward(self, batch: dict[str, torch.Tensor], log_kc: bool = False) -> torch.Tensor:
        x = batch["cues"].double()
        b = x.shape[0]
        t, m = self.feature.shape
        # nodes as flat indices into the (t, m) arrays, one entry per (pair, tree); each level walks only the
        # entries not yet at a leaf (most trees are far shallower than the deepest, so few entries go deep)
        feature, leaf, miss = self.feature.reshape(-1), self.is_leaf.reshape(-1), self.missing_left.reshape(-1)
        threshold, left, right = self.threshold.reshape(-1).double(), self.left.reshape(-1), self.right.reshape(-1)
        tree_base = torch.arange(t, dtype=torch.int64) * m
        node = tree_base.repeat(b)  # (b * t,) entry e = pair e // t, tree e % t
        active = torch.arange(b * t, dtype=torch.int64)
        for _ in range(self.depth):
            n = node[active]
            inner = ~leaf[n]
            if not bool(inner.any()):
                break
            active, n = active[inner], n[inner]
            v = x[torch.div(active, t, rounding_mode="floor"), feature[n]]
            go_left = torch.where(torch.isnan(v), miss[n], v <= threshold[n])
            node[active] = torch.where(go_left, left[n], right[n]) + tree_base[active % t]
        node = node.reshape(b, t)
        raw = self.value.reshape(-1)[node].double().sum(1) + self.baseline.double()
        return torch.stack([torch.zeros_like(raw), raw], dim=1).float()
