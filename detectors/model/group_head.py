"""Group regression head (seed 001): one class MLP and one box MLP per class group.

Every query gets C class logits and G box hypotheses, one per group head (the groups of
`detectors.model.groups`). The box a query reports is its top class's group's box; the next
layer's anchor is option A of the paper: the group-score-weighted mean of the G centres
(group score = summed sigmoid probabilities of the group's classes). Box coding and anchor
offsets are those of `heads.DetectionHead`.

Shapes (B frames, Q queries, D channels, C classes, G groups):

    query [B, Q, D], anchors [B, Q, 2] -> HeadOutput(
        logits [B, Q, C], encoded [B, Q, 10], boxes [B, Q, 9]   (top class's group),
        next_anchors [B, Q, 2]                                   (option A),
        group_encoded [B, Q, G, 10], group_boxes [B, Q, G, 9], group_scores [B, Q, G])
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor, nn

from detectors.model.bev import prior_bias
from detectors.model.groups import group_scores, select_group, weighted_centre
from detectors.model.heads import HeadOutput, box_mlp, decode_boxes, mlp


class GroupDetectionHead(nn.Module):
    """Sigmoid class logits (prior 0.01) and G anchor-relative boxes, one per class group."""

    def __init__(self, d_model: int, n_classes: int, class_group: Sequence[int],
                 offset_unit: float) -> None:
        super().__init__()
        if len(class_group) != n_classes:
            raise ValueError(f"class_group must list {n_classes} groups, got {len(class_group)}")
        self.offset_unit = offset_unit
        self.n_groups = max(class_group) + 1
        self.register_buffer("class_group", torch.as_tensor(class_group, dtype=torch.long),
                             persistent=False)
        self.cls = mlp(d_model, n_classes)
        nn.init.constant_(self.cls[-1].bias, prior_bias(0.01))
        self.boxes = nn.ModuleList(box_mlp(d_model) for _ in range(self.n_groups))

    def forward(self, query: Tensor, anchors: Tensor) -> HeadOutput:
        logits = self.cls(query)
        raw = torch.stack([head(query) for head in self.boxes], dim=-2)  # [B, Q, G, 10]
        centre = anchors[..., None, :] + raw[..., 0:2] * self.offset_unit
        group_encoded = torch.cat([centre, raw[..., 2:]], dim=-1)
        scores = group_scores(logits.detach(), self.class_group, self.n_groups)
        top = self.class_group[logits.argmax(dim=-1)]  # [B, Q] group of the top class
        encoded = select_group(group_encoded, top)
        refined = weighted_centre(centre.detach(), scores)
        return HeadOutput(logits=logits, encoded=encoded, boxes=decode_boxes(encoded),
                          next_anchors=refined, group_encoded=group_encoded,
                          group_boxes=decode_boxes(group_encoded), group_scores=scores)

