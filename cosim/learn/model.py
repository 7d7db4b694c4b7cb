"""The detector in PyTorch: a pillar encoder (PointNet per pillar), a scatter onto the bird's-eye grid,
a trimmed two-level 2D backbone and a centre-based head (a heatmap per class plus box regression), with
its loss. Written for this project after the PointPillars (Lang et al., 2019) and CenterPoint (Yin et
al., 2021) papers.

Intermediate fusion (:class:`PillarDetector` with ``fusion="intermediate"``): each agent's pillars, in its
own bird's-eye grid (:func:`cosim.learn.samples.agent_grid`), are encoded (one encoder, or one per agent
kind), then each ego cell takes the feature of the agent's pillar under its centre moved into the agent's
frame (:func:`warp_maps`: an index warp, any yaw), and the agents' maps are fused per cell by max (F-Cooper,
Chen et al. 2019) or by scaled dot-product attention of the ego's feature over the agents' (AttFuse, Xu et
al. 2022) before the backbone.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from cosim.learn.grid import POINT_FEATURES, REG_CHANNELS, Grid
from cosim.learn.samples import KINDS, agent_grid


def _conv(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]


class PillarDetector(nn.Module):
    """Pillars -> (B, C, ny, nx) pseudo-image -> backbone at strides 2 and 4 -> head at stride 2."""

    def __init__(self, grid: Grid, n_classes: int, width: int = 32, fusion: str = "none", fuse: str = "max",
                 encoders: str = "shared"):
        super().__init__()
        if grid.stride != 2:
            raise ValueError("the backbone's head works at stride 2")
        self.grid = grid
        self.n_classes = n_classes
        self.intermediate = fusion == "intermediate"
        self.fuse = fuse
        self.per_kind = self.intermediate and encoders == "kind"
        c = width
        self.pfn = nn.Linear(POINT_FEATURES, c, bias=False)
        self.pfn_bn = nn.BatchNorm1d(c)
        if self.per_kind:  # kinds after the first have their own encoder; the first uses pfn, pfn_bn
            self.kind_pfn = nn.ModuleList(nn.Linear(POINT_FEATURES, c, bias=False) for _ in KINDS[1:])
            self.kind_bn = nn.ModuleList(nn.BatchNorm1d(c) for _ in KINDS[1:])
        self.block1 = nn.Sequential(*_conv(c, 2 * c, 2), *_conv(2 * c, 2 * c))
        self.block2 = nn.Sequential(*_conv(2 * c, 3 * c, 2), *_conv(3 * c, 3 * c), *_conv(3 * c, 3 * c))
        self.up1 = nn.Sequential(nn.Conv2d(2 * c, 2 * c, 1, bias=False), nn.BatchNorm2d(2 * c), nn.ReLU(inplace=True))
        self.up2 = nn.Sequential(nn.ConvTranspose2d(3 * c, 2 * c, 2, 2, bias=False), nn.BatchNorm2d(2 * c),
                                 nn.ReLU(inplace=True))
        self.shared = nn.Sequential(*_conv(4 * c, 2 * c))
        self.heat = nn.Conv2d(2 * c, n_classes, 1)
        self.reg = nn.Conv2d(2 * c, REG_CHANNELS, 1)
        nn.init.constant_(self.heat.bias, -2.19)  # a prior of 0.1 per cell, as CenterNet

    def encode(self, features: torch.Tensor, mask: torch.Tensor, kinds: torch.Tensor | None = None
               ) -> torch.Tensor:
        """Pillar features (P, C): the PointNet of each pillar's points (per agent kind with ``kinds`` (P,))."""
        c = self.pfn.out_features
        point = torch.zeros(features.shape[0], features.shape[1], c, dtype=features.dtype, device=features.device)
        if not self.per_kind or kinds is None:
            point[mask] = F.relu(self.pfn_bn(self.pfn(features[mask])))
        else:
            for k in range(len(KINDS)):
                sel = mask & (kinds == k)[:, None]
                if not bool(sel.any()):
                    continue
                lin, bn = (self.pfn, self.pfn_bn) if k == 0 else (self.kind_pfn[k - 1], self.kind_bn[k - 1])
                point[sel] = F.relu(bn(lin(features[sel])))
        return point.max(dim=1).values

    def forward(self, features: torch.Tensor, mask: torch.Tensor, coords: torch.Tensor, batch_size: int,
                maps: dict[str, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``features`` (P, M, 9), ``mask`` (P, M) bool, ``coords`` (P, 3) long [batch, row, column].
        Intermediate fusion: ``coords`` [map, row, column] in the agents' grids, map = batch x J + agent,
        and ``maps`` with ``poses`` (B, J, 3) (yaw, x, y of each agent's frame in the ego's), ``kinds`` (B, J)
        and ``present`` (B, J) bool. Returns heatmap logits (B, K, H, W) and regression (B, 8, H, W)."""
        g = self.grid
        c = self.pfn.out_features
        if self.intermediate:
            if maps is None:
                raise ValueError("intermediate fusion needs the agents' poses (maps)")
            kinds = maps["kinds"].reshape(-1)[coords[:, 0]]
            pillar = self.encode(features, mask, kinds)
            warped, hit = warp_maps(pillar, coords, maps["poses"], maps["present"], g, agent_grid(g))
            x = fuse_maps(warped, hit, self.fuse)
        else:
            pillar = self.encode(features, mask)
            canvas = torch.zeros(batch_size * g.ny * g.nx, c, dtype=features.dtype, device=features.device)
            flat = (coords[:, 0] * g.ny + coords[:, 1]) * g.nx + coords[:, 2]
            canvas = canvas.index_put((flat,), pillar)
            x = canvas.view(batch_size, g.ny, g.nx, c).permute(0, 3, 1, 2)
        x1 = self.block1(x)
        x2 = self.block2(x1)
        u2 = self.up2(x2)[..., : x1.shape[2], : x1.shape[3]]
        y = self.shared(torch.cat([self.up1(x1), u2], dim=1))
        return self.heat(y), self.reg(y)


def warp_maps(pillar: torch.Tensor, coords: torch.Tensor, poses: torch.Tensor, present: torch.Tensor, grid: Grid,
              agent: Grid) -> tuple[torch.Tensor, torch.Tensor]:
    """The agents' pillar features in the ego grid: for each ego cell, the feature of the pillar of agent j
    whose cell (of ``agent``'s grid, in agent j's frame) holds the ego cell's centre moved into that frame.

    ``pillar`` (P, C); ``coords`` (P, 3) [map, row, column], map = b x J + j; ``poses`` (B, J, 3) yaw, x, y
    of agent j's frame in the ego's; ``present`` (B, J). Returns (B, J, C, ny, nx) features (0 where agent j
    has no pillar) and (B, J, ny, nx) bool: where it has one."""
    b, j = present.shape
    dev = pillar.device
    cx = grid.x_range[0] + (torch.arange(grid.nx, device=dev, dtype=torch.float64) + 0.5) * grid.pillar_m
    cy = grid.y_range[0] + (torch.arange(grid.ny, device=dev, dtype=torch.float64) + 0.5) * grid.pillar_m
    ex, ey = cx[None, :].expand(grid.ny, grid.nx), cy[:, None].expand(grid.ny, grid.nx)
    p = poses.reshape(b * j, 3).to(torch.float64)
    cos, sin = torch.cos(p[:, 0])[:, None, None], torch.sin(p[:, 0])[:, None, None]
    dx, dy = ex[None] - p[:, 1, None, None], ey[None] - p[:, 2, None, None]
    ax = cos * dx + sin * dy  # the ego cell centre in agent j's frame
    ay = -sin * dx + cos * dy
    col = torch.floor((ax - agent.x_range[0]) / agent.pillar_m).long()
    row = torch.floor((ay - agent.y_range[0]) / agent.pillar_m).long()
    inside = (col >= 0) & (col < agent.nx) & (row >= 0) & (row < agent.ny)
    maps = torch.arange(b * j, device=dev)[:, None, None]
    query = (maps * agent.ny + row.clamp(0, agent.ny - 1)) * agent.nx + col.clamp(0, agent.nx - 1)
    keys = (coords[:, 0] * agent.ny + coords[:, 1]) * agent.nx + coords[:, 2]
    order = torch.argsort(keys)
    keys_s = keys[order]
    pos = torch.searchsorted(keys_s, query.reshape(-1)).clamp(max=max(len(keys_s) - 1, 0))
    if len(keys_s):
        hit = (keys_s[pos] == query.reshape(-1)) & inside.reshape(-1)
    else:
        hit = torch.zeros(query.numel(), dtype=torch.bool, device=dev)
    hit = hit & present.reshape(-1)[:, None].expand(b * j, grid.ny * grid.nx).reshape(-1)
    c = pillar.shape[1]
    out = torch.zeros(b * j * grid.ny * grid.nx, c, dtype=pillar.dtype, device=dev)
    if len(keys_s):
        idx = torch.nonzero(hit).squeeze(1)
        out = out.index_put((idx,), pillar[order[pos[idx]]])
    out = out.view(b, j, grid.ny, grid.nx, c).permute(0, 1, 4, 2, 3)
    return out, hit.view(b, j, grid.ny, grid.nx)


def fuse_maps(warped: torch.Tensor, hit: torch.Tensor, how: str) -> torch.Tensor:
    """(B, C, ny, nx): the agents' warped maps (B, J, C, ny, nx) fused per cell, by max over the agents
    (F-Cooper's maxout; features are ReLU outputs, so an agent without a pillar there, at 0, never wins) or
    by attention: softmax over the agents with a pillar there of <ego feature, agent feature> / sqrt(C),
    weighting the agents' features (AttFuse)."""
    if how == "max":
        return warped.max(dim=1).values
    c = warped.shape[2]
    ego = warped[:, :1]
    score = (warped * ego).sum(dim=2) / math.sqrt(c)  # (B, J, ny, nx)
    allowed = hit.clone()
    allowed[:, 0] |= ~hit.any(dim=1)  # a cell no agent has a pillar in: the ego's (zero) feature
    score = score.masked_fill(~allowed, float("-inf"))
    w = torch.softmax(score, dim=1)
    return (w[:, :, None] * warped).sum(dim=1)


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4), normalised by the number of peaks."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).float()
    neg = 1.0 - pos
    pos_loss = torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = torch.log(1 - p) * p ** 2 * (1 - target) ** 4 * neg
    n = pos.sum().clamp(min=1.0)
    return -(pos_loss.sum() + neg_loss.sum()) / n


def regression_loss(reg: torch.Tensor, target: torch.Tensor, index: torch.Tensor, mask: torch.Tensor
                    ) -> torch.Tensor:
    """L1 between the predicted and the true regression at the objects' centre cells."""
    b, ch, h, w = reg.shape
    pred = reg.view(b, ch, h * w).gather(2, index.unsqueeze(1).expand(b, ch, index.shape[1])).permute(0, 2, 1)
    m = mask.unsqueeze(2)
    return (F.l1_loss(pred * m, target * m, reduction="sum")) / (m.sum() * ch).clamp(min=1.0)


def peaks(logits: torch.Tensor) -> torch.Tensor:
    """Heatmap probabilities kept only at 3x3 local maxima (the head's own non-maximum suppression)."""
    p = torch.sigmoid(logits)
    return p * (F.max_pool2d(p, 3, 1, 1) == p).float()
