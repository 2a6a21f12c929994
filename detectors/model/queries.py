"""Query initialisation from a class heatmap, as TransFusion does.

A heatmap head predicts, per class, the probability that an object centre lies in each cell
of the fine BEV map (trained with a Gaussian focal target, see detectors.losses). The Q
highest local maxima over all classes become the queries: their anchor is the cell centre,
their content is the BEV feature at that cell plus an embedding of the heatmap class.

Shapes (B frames, D channels, C classes, H x W fine grid, Q queries):

    features [B, D, H, W] -> QueryInit(heatmap [B, C, H, W] logits, content [B, Q, D],
                                      anchors [B, Q, 2] metres, labels [B, Q], scores [B, Q])
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from detectors.model.bev import BEVGrid, prior_bias


class QueryInit(NamedTuple):
    """Heatmap logits and the queries drawn from them (shapes in the module docstring)."""

    heatmap: Tensor
    content: Tensor
    anchors: Tensor
    labels: Tensor
    scores: Tensor


class HeatmapQueries(nn.Module):
    """Heatmap head + top-K local-maximum query selection.

    `keep_all_classes` lists class indices exempt from the 3x3 local-maximum suppression
    (small objects that stand close together: TransFusion exempts pedestrians and cones).
    """

    def __init__(self, d_model: int, n_classes: int, n_queries: int, grid: BEVGrid,
                 keep_all_classes: tuple[int, ...] = ()) -> None:
        super().__init__()
        self.grid = grid
        self.n_queries = n_queries
        self.n_classes = n_classes
        self.keep_all_classes = tuple(keep_all_classes)
        self.head = nn.Sequential(
            nn.Conv2d(d_model, d_model, 3, padding=1, bias=False), nn.BatchNorm2d(d_model),
            nn.ReLU(inplace=True), nn.Conv2d(d_model, n_classes, 1))
        nn.init.constant_(self.head[-1].bias, prior_bias(0.1))
        self.class_embed = nn.Linear(n_classes, d_model)
        self.register_buffer("centres", grid.centres(), persistent=False)

    def forward(self, features: Tensor) -> QueryInit:
        b, d, h, w = features.shape
        if (h, w) != (self.grid.size, self.grid.size):
            raise ValueError(f"features must be {self.grid.size}x{self.grid.size}, got {h}x{w}")
        heatmap = self.head(features)
        heat = heatmap.detach().sigmoid()
        local_max = F.max_pool2d(heat, 3, stride=1, padding=1)
        if self.keep_all_classes:
            keep = list(self.keep_all_classes)
            local_max[:, keep] = heat[:, keep]
        heat = heat * (heat == local_max)
        q = min(self.n_queries, self.n_classes * h * w)
        scores, flat = heat.view(b, -1).topk(q, dim=1)
        labels = torch.div(flat, h * w, rounding_mode="floor")
        cells = flat % (h * w)
        tokens = features.flatten(2).transpose(1, 2)  # [B, HW, D]
        content = tokens.gather(1, cells[..., None].expand(-1, -1, d))
        content = content + self.class_embed(F.one_hot(labels, self.n_classes).float())
        anchors = self.centres[cells]
        return QueryInit(heatmap=heatmap, content=content, anchors=anchors, labels=labels,
                         scores=scores)
