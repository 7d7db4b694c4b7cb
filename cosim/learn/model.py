"""The detector in PyTorch: a pillar encoder (PointNet per pillar), a scatter onto the bird's-eye grid,
a trimmed two-level 2D backbone and a centre-based head (a heatmap per class plus box regression), with
its loss. Written for this project after the PointPillars (Lang et al., 2019) and CenterPoint (Yin et
al., 2021) papers.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.nn import functional as F

from cosim.learn.grid import POINT_FEATURES, REG_CHANNELS, Grid


def _conv(cin: int, cout: int, stride: int = 1) -> list[nn.Module]:
    return [nn.Conv2d(cin, cout, 3, stride, 1, bias=False), nn.BatchNorm2d(cout), nn.ReLU(inplace=True)]


class PillarDetector(nn.Module):
    """Pillars -> (B, C, ny, nx) pseudo-image -> backbone at strides 2 and 4 -> head at stride 2."""

    def __init__(self, grid: Grid, n_classes: int, width: int = 32):
        super().__init__()
        if grid.stride != 2:
            raise ValueError("the backbone's head works at stride 2")
        self.grid = grid
        self.n_classes = n_classes
        c = width
        self.pfn = nn.Linear(POINT_FEATURES, c, bias=False)
        self.pfn_bn = nn.BatchNorm1d(c)
        self.block1 = nn.Sequential(*_conv(c, 2 * c, 2), *_conv(2 * c, 2 * c))
        self.block2 = nn.Sequential(*_conv(2 * c, 3 * c, 2), *_conv(3 * c, 3 * c), *_conv(3 * c, 3 * c))
        self.up1 = nn.Sequential(nn.Conv2d(2 * c, 2 * c, 1, bias=False), nn.BatchNorm2d(2 * c), nn.ReLU(inplace=True))
        self.up2 = nn.Sequential(nn.ConvTranspose2d(3 * c, 2 * c, 2, 2, bias=False), nn.BatchNorm2d(2 * c),
                                 nn.ReLU(inplace=True))
        self.shared = nn.Sequential(*_conv(4 * c, 2 * c))
        self.heat = nn.Conv2d(2 * c, n_classes, 1)
        self.reg = nn.Conv2d(2 * c, REG_CHANNELS, 1)
        nn.init.constant_(self.heat.bias, -2.19)  # a prior of 0.1 per cell, as CenterNet

    def forward(self, features: torch.Tensor, mask: torch.Tensor, coords: torch.Tensor, batch_size: int
                ) -> tuple[torch.Tensor, torch.Tensor]:
        """``features`` (P, M, 9), ``mask`` (P, M) bool, ``coords`` (P, 3) long [batch, row, column].
        Returns heatmap logits (B, K, H, W) and regression (B, 8, H, W)."""
        g = self.grid
        c = self.pfn.out_features
        point = torch.zeros(features.shape[0], features.shape[1], c, dtype=features.dtype, device=features.device)
        point[mask] = F.relu(self.pfn_bn(self.pfn(features[mask])))
        pillar = point.max(dim=1).values
        canvas = torch.zeros(batch_size * g.ny * g.nx, c, dtype=features.dtype, device=features.device)
        flat = (coords[:, 0] * g.ny + coords[:, 1]) * g.nx + coords[:, 2]
        canvas = canvas.index_put((flat,), pillar)
        x = canvas.view(batch_size, g.ny, g.nx, c).permute(0, 3, 1, 2)
        x1 = self.block1(x)
        x2 = self.block2(x1)
        u2 = self.up2(x2)[..., : x1.shape[2], : x1.shape[3]]
        y = self.shared(torch.cat([self.up1(x1), u2], dim=1))
        return self.heat(y), self.reg(y)


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
