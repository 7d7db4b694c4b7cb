"""The detector in PyTorch: a pillar encoder (PointNet per pillar), a scatter onto the bird's-eye grid,
a trimmed two-level 2D backbone and a centre-based head (a heatmap per class plus box regression), with
its loss. Written for this project after the PointPillars (Lang et al., 2019) and CenterPoint (Yin et
al., 2021) papers.

Intermediate fusion (:class:`PillarDetector` with ``fusion="intermediate"``): each agent's pillars, in its
own bird's-eye grid (:func:`cosim.learn.samples.agent_grid`), are encoded (one encoder, or one per agent
kind), then each ego cell takes the feature of the agent's pillar under its centre moved into the agent's
frame (:func:`cosim.learn.grid.warp_index`: an index warp, any yaw, computed with the batch), and the agents'
features are fused per cell by max (F-Cooper, Chen et al. 2019) or by scaled dot-product attention of the
ego's feature over the agents' (AttFuse, Xu et al. 2022) before the backbone (:func:`fuse`). Pillars and
hits are sparse lists: no agent's map is ever made dense.
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from cosim.learn.grid import L1_CHANNELS, POINT_FEATURES, REG_CHANNELS, Grid
from cosim.learn.samples import KINDS


def _conv(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]


class PillarDetector(nn.Module):
    """Pillars -> (B, C, ny, nx) pseudo-image -> backbone at strides 2 and 4 -> head at stride 2."""

    def __init__(self, grid: Grid, n_classes: int, width: int = 32, fusion: str = "none", fuse: str = "max",
                 encoders: str = "shared", n_sensors: int = 0):
        super().__init__()
        if grid.stride != 2:
            raise ValueError("the backbone's head works at stride 2")
        self.grid = grid
        self.n_classes = n_classes
        self.intermediate = fusion == "intermediate"
        self.fuse = fuse
        if encoders == "sensor" and self.intermediate and n_sensors < 1:
            raise ValueError("per-sensor encoders need the number of sensors")
        self.per_agent = self.intermediate and encoders in ("kind", "sensor")
        c = width
        self.pfn = nn.Linear(POINT_FEATURES, c, bias=False)
        self.pfn_bn = nn.BatchNorm1d(c)
        self._encoders = [(self.pfn, self.pfn_bn)]
        if self.per_agent:  # encoders after the first have their own layers; the first uses pfn, pfn_bn
            prefix, n = ("kind", len(KINDS)) if encoders == "kind" else ("sensor", n_sensors)
            lins = nn.ModuleList(nn.Linear(POINT_FEATURES, c, bias=False) for _ in range(n - 1))
            bns = nn.ModuleList(nn.BatchNorm1d(c) for _ in range(n - 1))
            setattr(self, f"{prefix}_pfn", lins)
            setattr(self, f"{prefix}_bn", bns)
            self._encoders += list(zip(lins, bns, strict=True))
        self.block1 = nn.Sequential(*_conv(c, 2 * c, 2), *_conv(2 * c, 2 * c))
        self.block2 = nn.Sequential(*_conv(2 * c, 3 * c, 2), *_conv(3 * c, 3 * c), *_conv(3 * c, 3 * c))
        self.up1 = nn.Sequential(nn.Conv2d(2 * c, 2 * c, 1, bias=False), nn.BatchNorm2d(2 * c), nn.ReLU(inplace=True))
        self.up2 = nn.Sequential(nn.ConvTranspose2d(3 * c, 2 * c, 2, 2, bias=False), nn.BatchNorm2d(2 * c),
                                 nn.ReLU(inplace=True))
        self.shared = nn.Sequential(*_conv(4 * c, 2 * c))
        self.heat = nn.Conv2d(2 * c, n_classes, 1)
        self.reg = nn.Conv2d(2 * c, REG_CHANNELS, 1)
        nn.init.constant_(self.heat.bias, -2.19)  # a prior of 0.1 per cell, as CenterNet

    def encode(self, features: torch.Tensor, counts: torch.Tensor, encoder: torch.Tensor | None = None
               ) -> torch.Tensor:
        """Pillar features (P, C): the PointNet of each pillar's points, ``features`` (K, 9) of the points,
        pillar after pillar, ``counts`` (P,) points per pillar (per agent kind or sensor with ``encoder`` (P,),
        each pillar's encoder): a linear layer, batch norm over the points, ReLU, then the maximum over each
        pillar's points."""
        c = self.pfn.out_features
        if not self.per_agent or encoder is None:
            point = F.relu(self.pfn_bn(self.pfn(features)))
        else:
            point = features.new_zeros(features.shape[0], c)
            of_point = encoder.repeat_interleave(counts)
            for k, (lin, bn) in enumerate(self._encoders):
                sel = of_point == k
                if not bool(sel.any()):
                    continue
                point = point.index_put((torch.nonzero(sel).squeeze(1),), F.relu(bn(lin(features[sel]))))
        return torch.segment_reduce(point, "max", lengths=counts, unsafe=True)

    def forward(self, features: torch.Tensor, counts: torch.Tensor, coords: torch.Tensor, batch_size: int,
                maps: dict[str, torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``features`` (K, 9) of the pillars' points, pillar after pillar, ``counts`` (P,) long points per
        pillar, ``coords`` (P, 3) long [batch, row, column] of each pillar.
        Intermediate fusion: ``coords`` [map, row, column] in the agents' grids, map = batch x J + agent,
        and ``maps`` with ``encoder`` (B, J) and the warp's hits ``cell``, ``src``, ``ego``
        (:func:`cosim.learn.grid.warp_index`). Returns heatmap logits (B, K, H, W) and regression (B, 9, H, W)."""
        g = self.grid
        c = self.pfn.out_features
        if self.intermediate:
            if maps is None:
                raise ValueError("intermediate fusion needs the agents' poses (maps)")
            pillars = self.encode(features, counts, maps["encoder"].reshape(-1)[coords[:, 0]])
            fused = fuse(pillars, maps["cell"], maps["src"], maps["ego"], batch_size * g.ny * g.nx, self.fuse)
            x = fused.view(batch_size, g.ny, g.nx, c).permute(0, 3, 1, 2)
        else:
            pillars = self.encode(features, counts)
            canvas = torch.zeros(batch_size * g.ny * g.nx, c, dtype=features.dtype, device=features.device)
            flat = (coords[:, 0] * g.ny + coords[:, 1]) * g.nx + coords[:, 2]
            canvas = canvas.index_put((flat,), pillars)
            x = canvas.view(batch_size, g.ny, g.nx, c).permute(0, 3, 1, 2)
        x1 = self.block1(x)
        x2 = self.block2(x1)
        u2 = self.up2(x2)[..., : x1.shape[2], : x1.shape[3]]
        y = self.shared(torch.cat([self.up1(x1), u2], dim=1))
        return self.heat(y), self.reg(y)


def fuse(pillars: torch.Tensor, cell: torch.Tensor, src: torch.Tensor, ego: torch.Tensor, n_cells: int, how: str
         ) -> torch.Tensor:
    """(n_cells, C): the agents' pillar features ``pillars`` (P, C) fused per ego cell over the warp's hits
    (:func:`cosim.learn.grid.warp_index`: ``cell`` in ascending order, ``src`` the pillar, ``ego`` the ego's
    own), by max over the agents (F-Cooper's maxout; features are ReLU outputs, and a cell no agent has a
    pillar in is 0) or by attention: softmax over the agents with a pillar in the cell of <ego feature, agent
    feature> / sqrt(C), weighting the agents' features (AttFuse; the ego's feature is 0 where it has no
    pillar)."""
    c = pillars.shape[1]
    feat = pillars[src]
    if how == "max":
        lengths = torch.bincount(cell, minlength=n_cells)
        return torch.segment_reduce(feat, "max", lengths=lengths, unsafe=True, initial=0.0)
    own = pillars.new_zeros(n_cells, c).index_put((cell[ego],), feat[ego])
    score = (feat * own[cell]).sum(dim=1) / math.sqrt(c)
    top = score.new_full((n_cells,), float("-inf")).scatter_reduce(0, cell, score, "amax", include_self=True)
    w = torch.exp(score - top[cell])
    w = w / score.new_zeros(n_cells).index_add(0, cell, w)[cell]
    return pillars.new_zeros(n_cells, c).index_add(0, cell, w[:, None] * feat)


def focal_loss(logits: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss (alpha 2, beta 4), normalised by the number of peaks."""
    p = torch.sigmoid(logits).clamp(1e-4, 1 - 1e-4)
    pos = target.eq(1).float()
    neg = 1.0 - pos
    pos_loss = torch.log(p) * (1 - p) ** 2 * pos
    neg_loss = torch.log(1 - p) * p ** 2 * (1 - target) ** 4 * neg
    n = pos.sum().clamp(min=1.0)
    return -(pos_loss.sum() + neg_loss.sum()) / n


def regression_loss(reg: torch.Tensor, target: torch.Tensor, index: torch.Tensor, mask: torch.Tensor,
                    direction_weight: float = 0.2) -> torch.Tensor:
    """At the objects' centre cells: L1 between the predicted and the true box channels (the first
    :data:`~cosim.learn.grid.L1_CHANNELS`), plus ``direction_weight`` x the binary cross-entropy of the
    direction logit (PointPillars' direction classifier and weight)."""
    b, ch, h, w = reg.shape
    pred = reg.view(b, ch, h * w).gather(2, index.unsqueeze(1).expand(b, ch, index.shape[1])).permute(0, 2, 1)
    m = mask.unsqueeze(2)
    n = m.sum()
    l1 = F.l1_loss(pred[..., :L1_CHANNELS] * m, target[..., :L1_CHANNELS] * m, reduction="sum")
    bce = F.binary_cross_entropy_with_logits(pred[..., L1_CHANNELS:], target[..., L1_CHANNELS:], weight=m,
                                             reduction="sum")
    return l1 / (n * L1_CHANNELS).clamp(min=1.0) + direction_weight * bce / n.clamp(min=1.0)


def peaks(logits: torch.Tensor) -> torch.Tensor:
    """Heatmap probabilities kept only at 3x3 local maxima (the head's own non-maximum suppression)."""
    p = torch.sigmoid(logits)
    return p * (F.max_pool2d(p, 3, 1, 1) == p).float()
