"""Bird's-eye-view encoding: points -> pillar grid -> small CNN backbone, and positional encoding.

Shapes (B frames, P_b points of frame b, F point features, C0 pillar channels):

    points          list of B tensors [P_b, F]  ego frame, columns in the sensor's FEATURES order
                                                (first three x, y, z in metres)
    PillarEncoder   -> [B, C0 + 1, S, S]         S = grid.size cells of grid.cell metres
    BEVBackbone     -> BEVFeatures(fine [B, D, S/2, S/2], coarse [B, D, S/4, S/4])

The grid is square and centred on the ego: cell (i, j) (row i along y, column j along x)
covers x in [origin + j*cell, origin + (j+1)*cell), likewise y with i.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor, nn


@dataclass(frozen=True)
class BEVGrid:
    """A square BEV grid centred on the ego: `size` x `size` cells of `cell` metres."""

    size: int = 128
    cell: float = 0.8

    @property
    def origin(self) -> float:
        """x (and y) of the grid's lower edge in metres, e.g. -51.2."""
        return -0.5 * self.size * self.cell

    @property
    def half_extent(self) -> float:
        """Half the side length in metres (the grid spans [-half_extent, half_extent))."""
        return 0.5 * self.size * self.cell

    def strided(self, stride: int) -> BEVGrid:
        """The grid of a feature map `stride` times coarser."""
        if self.size % stride:
            raise ValueError(f"stride {stride} does not divide grid size {self.size}")
        return BEVGrid(size=self.size // stride, cell=self.cell * stride)

    def centres(self, device: torch.device | None = None) -> Tensor:
        """`[size*size, 2]` (x, y) of every cell centre in metres, row-major (row = y index)."""
        c = self.origin + (torch.arange(self.size, device=device, dtype=torch.float32) + 0.5) \
            * self.cell
        yy, xx = torch.meshgrid(c, c, indexing="ij")
        return torch.stack([xx.reshape(-1), yy.reshape(-1)], dim=-1)


class PillarEncoder(nn.Module):
    """PointPillars-style encoder: a per-point linear layer, max-pooled into grid cells.

    Each point gets its raw features plus its offset from its cell centre (in cells); a
    Linear + BatchNorm + ReLU maps it to `channels`, and a scatter-max pools each cell. A
    log(1 + count) occupancy channel is appended. Points outside the grid are dropped.
    """

    def __init__(self, n_features: int, channels: int, grid: BEVGrid) -> None:
        super().__init__()
        self.grid = grid
        self.n_features = n_features
        self.channels = channels
        self.input_norm = nn.BatchNorm1d(n_features + 2)
        self.linear = nn.Linear(n_features + 2, channels, bias=False)
        self.norm = nn.BatchNorm1d(channels)

    @property
    def out_channels(self) -> int:
        return self.channels + 1

    def forward(self, points: list[Tensor]) -> Tensor:
        """`points`: B tensors `[P_b, F]` -> pillar map `[B, channels + 1, S, S]`."""
        g = self.grid
        n_cells = g.size * g.size
        device = self.linear.weight.device
        feats, flat = [], []
        for b, p in enumerate(points):
            if p.ndim != 2 or p.shape[1] != self.n_features:
                raise ValueError(f"points[{b}] must have shape [P, {self.n_features}], "
                                 f"got {tuple(p.shape)}")
            p = p.to(device=device, dtype=torch.float32)
            col = torch.floor((p[:, 0] - g.origin) / g.cell)
            row = torch.floor((p[:, 1] - g.origin) / g.cell)
            keep = (col >= 0) & (col < g.size) & (row >= 0) & (row < g.size)
            p, col, row = p[keep], col[keep], row[keep]
            offset = torch.stack([(p[:, 0] - g.origin) / g.cell - col - 0.5,
                                  (p[:, 1] - g.origin) / g.cell - row - 0.5], dim=1)
            feats.append(torch.cat([p, offset], dim=1))
            flat.append(b * n_cells + row.long() * g.size + col.long())
        x = torch.cat(feats) if feats else torch.zeros(0, self.n_features + 2, device=device)
        index = torch.cat(flat) if flat else torch.zeros(0, dtype=torch.long, device=device)
        n_total = len(points) * n_cells
        # BatchNorm needs two points to normalise in training; fewer only happens on empty
        # clouds, which then pass un-normalised.
        use_norm = x.shape[0] > (1 if self.training else 0)
        x = self.input_norm(x) if use_norm else x
        x = self.linear(x)
        x = torch.relu(self.norm(x) if use_norm else x)
        pooled = torch.zeros(n_total, self.channels, device=device, dtype=x.dtype)
        pooled = pooled.scatter_reduce(0, index[:, None].expand(-1, self.channels), x,
                                       reduce="amax", include_self=True)
        count = torch.zeros(n_total, device=device).index_add_(
            0, index, torch.ones_like(index, dtype=torch.float32))
        out = torch.cat([pooled, torch.log1p(count)[:, None]], dim=1)
        return out.view(len(points), g.size, g.size, self.out_channels).permute(0, 3, 1, 2) \
            .contiguous()


def _conv(c_in: int, c_out: int, stride: int = 1) -> nn.Sequential:
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1, bias=False),
                         nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class BEVFeatures(NamedTuple):
    """Backbone outputs: `fine [B, D, S/2, S/2]` (heatmap, query features) and
    `coarse [B, D, S/4, S/4]` (cross-attention tokens)."""

    fine: Tensor
    coarse: Tensor


class BEVBackbone(nn.Module):
    """A two-stage CNN (SECOND-like, tiny) with an FPN-style merge back to stride 2.

    pillar map [B, C_in, S, S] -> stage 1 (stride 2, c1 ch) -> stage 2 (stride 4, c2 ch);
    fine = conv(cat(stage1, up(stage2))) with `d_model` channels at stride 2,
    coarse = 1x1 conv(stage2) with `d_model` channels at stride 4.
    """

    def __init__(self, in_channels: int, c1: int, c2: int, d_model: int,
                 blocks: tuple[int, int] = (1, 1)) -> None:
        super().__init__()
        self.stage1 = nn.Sequential(_conv(in_channels, c1, 2),
                                    *[_conv(c1, c1) for _ in range(blocks[0])])
        self.stage2 = nn.Sequential(_conv(c1, c2, 2), *[_conv(c2, c2) for _ in range(blocks[1])])
        self.up = nn.Sequential(nn.ConvTranspose2d(c2, c1, 2, stride=2, bias=False),
                                nn.BatchNorm2d(c1), nn.ReLU(inplace=True))
        self.fuse = _conv(2 * c1, d_model)
        self.tokens = nn.Conv2d(c2, d_model, 1)

    def forward(self, x: Tensor) -> BEVFeatures:
        s1 = self.stage1(x)
        s2 = self.stage2(s1)
        fine = self.fuse(torch.cat([s1, self.up(s2)], dim=1))
        return BEVFeatures(fine=fine, coarse=self.tokens(s2))


class PillarTokens(nn.Module):
    """Cross-attention tokens at the pillar grid's own resolution (stride 1, seed 000's
    128 x 128 at 0.8 m): a 1x1 conv of the pillar map plus the fine map upsampled x2.

    pillar map [B, C_in, S, S], fine [B, D, S/2, S/2] -> [B, D, S, S]
    """

    def __init__(self, in_channels: int, d_model: int) -> None:
        super().__init__()
        self.proj = nn.Conv2d(in_channels, d_model, 1)

    def forward(self, pillars: Tensor, fine: Tensor) -> Tensor:
        return self.proj(pillars) + nn.functional.interpolate(fine, scale_factor=2.0,
                                                              mode="nearest")


class PositionEncoding(nn.Module):
    """Learned positional encoding of BEV positions (TransFusion's PositionEmbeddingLearned).

    `xy [..., 2]` metres -> `[..., d_model]`; positions are divided by `scale` (the grid's
    half extent) first. The same module encodes BEV tokens and query anchors, so queries and
    keys live in one positional space.
    """

    def __init__(self, d_model: int, scale: float) -> None:
        super().__init__()
        self.scale = scale
        self.mlp = nn.Sequential(nn.Linear(2, d_model), nn.ReLU(inplace=True),
                                 nn.Linear(d_model, d_model))

    def forward(self, xy: Tensor) -> Tensor:
        return self.mlp(xy / self.scale)


def prior_bias(prior: float) -> float:
    """Bias that makes a sigmoid output `prior` at initialisation (focal-loss heads)."""
    return -math.log((1 - prior) / prior)
