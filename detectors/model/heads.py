"""Class and box heads applied after every decoder layer, and the box coding.

Box layout (contract): `x y z w l h yaw vx vy` in metres / radians / m/s, ego frame.
Regression space (what the L1 loss sees, `[..., 10]`): `x y z log(w) log(l) log(h)
sin(yaw) cos(yaw) vx vy`. The head predicts the centre as an offset from the query's anchor
(in units of `offset_unit` metres), so boxes are refined relative to the anchor and the next
layer's anchor is this layer's centre.

Shapes (B frames, Q queries, D channels, C classes):

    query [B, Q, D], anchors [B, Q, 2] -> HeadOutput(logits [B, Q, C], encoded [B, Q, 10],
                                                     boxes [B, Q, 9], next_anchors [B, Q, 2])

The group regression head (`group_head.GroupDetectionHead`) returns the same tuple with its
group fields filled in; a unified head leaves them None.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn

from detectors.model.bev import prior_bias

CODE_SIZE = 10
LOG_SIZE_RANGE = (-3.0, 3.5)  # sizes between 5 cm and 33 m


def encode_boxes(boxes: Tensor) -> Tensor:
    """`[..., 9]` boxes -> `[..., 10]` regression space (log sizes, sin/cos yaw)."""
    size = boxes[..., 3:6].clamp_min(1e-3).log()
    yaw = boxes[..., 6:7]
    return torch.cat([boxes[..., 0:3], size, yaw.sin(), yaw.cos(), boxes[..., 7:9]], dim=-1)


def decode_boxes(encoded: Tensor) -> Tensor:
    """`[..., 10]` regression space -> `[..., 9]` boxes (exp sizes, atan2 yaw)."""
    size = encoded[..., 3:6].clamp(*LOG_SIZE_RANGE).exp()
    yaw = torch.atan2(encoded[..., 6:7], encoded[..., 7:8])
    return torch.cat([encoded[..., 0:3], size, yaw, encoded[..., 8:10]], dim=-1)


class HeadOutput(NamedTuple):
    """Per-layer head outputs (shapes in the module docstring); `next_anchors` is where the
    next decoder layer anchors its queries (a unified head: this layer's centres). The group
    fields (`[B, Q, G, 10]`, `[B, Q, G, 9]`, `[B, Q, G]`) are None for a unified head."""

    logits: Tensor
    encoded: Tensor
    boxes: Tensor
    next_anchors: Tensor
    group_encoded: Tensor | None = None
    group_boxes: Tensor | None = None
    group_scores: Tensor | None = None


def mlp(d_model: int, d_out: int) -> nn.Sequential:
    """Linear -> ReLU -> Linear, `d_model` -> `d_out` (the heads' MLP)."""
    return nn.Sequential(nn.Linear(d_model, d_model), nn.ReLU(inplace=True),
                         nn.Linear(d_model, d_out))


def box_mlp(d_model: int,
            mean_log_size: tuple[float, float, float] = (0.64, 1.5, 0.5)) -> nn.Sequential:
    """The box MLP (dx dy z logw logl logh sin cos vx vy), initialised to a box of
    `mean_log_size` at the anchor with yaw 0."""
    box = mlp(d_model, CODE_SIZE - 2 + 2)
    nn.init.zeros_(box[-1].weight)
    with torch.no_grad():
        box[-1].bias.zero_()
        box[-1].bias[3:6] = torch.tensor(mean_log_size)
        box[-1].bias[7] = 1.0  # cos(yaw) = 1: yaw 0
    return box


class DetectionHead(nn.Module):
    """Sigmoid class logits (focal-loss prior 0.01) and an anchor-relative box."""

    def __init__(self, d_model: int, n_classes: int, offset_unit: float,
                 mean_log_size: tuple[float, float, float] = (0.64, 1.5, 0.5)) -> None:
        super().__init__()
        self.offset_unit = offset_unit
        self.cls = mlp(d_model, n_classes)
        self.box = box_mlp(d_model, mean_log_size)
        nn.init.constant_(self.cls[-1].bias, prior_bias(0.01))

    def forward(self, query: Tensor, anchors: Tensor) -> HeadOutput:
        logits = self.cls(query)
        raw = self.box(query)
        centre = anchors + raw[..., 0:2] * self.offset_unit
        encoded = torch.cat([centre, raw[..., 2:]], dim=-1)
        return HeadOutput(logits=logits, encoded=encoded, boxes=decode_boxes(encoded),
                          next_anchors=centre)
