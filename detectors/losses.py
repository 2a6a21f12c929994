"""Training losses: Hungarian matching, sigmoid focal class loss, L1 box loss, heatmap loss.

DETR3D/PETR style: every decoder layer's predictions are matched to the ground truth
independently with `scipy.optimize.linear_sum_assignment` on a focal class cost plus a
weighted L1 cost in regression space (heads.encode_boxes); the focal class loss covers all
queries (unmatched ones learn "no object" as all-zero targets), the L1 box loss the matched
ones; every layer contributes (auxiliary losses). The TransFusion heatmap gets a CenterNet
Gaussian focal loss.

Group regression heads (seed 001, Sec. III-C): the output dict then holds every group
head's box (`pred_group_encoded [L, B, Q, G, 10]`); the matching cost compares a
ground-truth box of class c with each query's box *of c's group head* (the cost matrix keeps
the unified size, queries x ground truth), and the L1 box loss of a matched pair reaches only
that head.

Targets: one `Target(labels [G] int64, boxes [G, 9] float32)` per frame, boxes in the
detector's ego frame (x y z w l h yaw vx vy). Losses are normalised by the number of
ground-truth boxes in the batch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from scipy.optimize import linear_sum_assignment
from torch import Tensor

from detectors.model.bev import BEVGrid
from detectors.model.heads import encode_boxes

# x y z log(w) log(l) log(h) sin cos vx vy (as DETR3D's code_weights)
CODE_WEIGHTS = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2)


class Target(NamedTuple):
    """Ground truth of one frame: `labels [G]` int64 class indices, `boxes [G, 9]` float32."""

    labels: Tensor
    boxes: Tensor


class Match(NamedTuple):
    """Matched pairs of one frame: `query [M]` indices into Q, `gt [M]` indices into G."""

    query: Tensor
    gt: Tensor


def focal_cost(logits: Tensor, alpha: float = 0.25, gamma: float = 2.0) -> Tensor:
    """`[Q, C]` logits -> `[Q, C]` cost of assigning each query to each class (DETR3D)."""
    p = logits.sigmoid()
    neg = (1 - alpha) * p.pow(gamma) * -F.logsigmoid(-logits)
    pos = alpha * (1 - p).pow(gamma) * -F.logsigmoid(logits)
    return pos - neg


def _group_boxes(encoded: Tensor, labels: Tensor, class_group: Tensor | None) -> Tensor:
    """One frame's `[Q, G_h, 10]` group boxes -> `[Q, T, 10]`: for each of the T ground
    truths (`labels [T]`), every query's box of that ground truth's group head."""
    if class_group is None:
        raise ValueError("group boxes need class_group (the group of every class)")
    return encoded[:, class_group.to(labels.device)[labels]]


class HungarianMatcher:
    """One-to-one assignment of queries to ground truth minimising the DETR3D cost.

    `encoded` is `[B, Q, 10]` (unified head) or `[B, Q, G_h, 10]` with `class_group [C]`
    (group heads: each ground truth is compared with its own group's box of every query)."""

    def __init__(self, cost_class: float = 2.0, cost_box: float = 0.25) -> None:
        self.cost_class = cost_class
        self.cost_box = cost_box

    @torch.no_grad()
    def __call__(self, logits: Tensor, encoded: Tensor, targets: list[Target],
                 class_group: Tensor | None = None) -> list[Match]:
        """`logits [B, Q, C]`, `encoded [B, Q, 10]` or `[B, Q, G_h, 10]` -> B matches."""
        weights = torch.tensor(CODE_WEIGHTS, dtype=encoded.dtype, device=encoded.device)
        matches = []
        for b, target in enumerate(targets):
            if len(target.labels) == 0:
                empty = torch.zeros(0, dtype=torch.long)
                matches.append(Match(empty, empty))
                continue
            cls = focal_cost(logits[b])[:, target.labels]  # [Q, G]
            gt = encode_boxes(target.boxes.to(encoded)) * weights
            if encoded.ndim == 4:
                own = _group_boxes(encoded[b], target.labels, class_group)  # [Q, G, 10]
                box = ((own * weights - gt[None]).abs()).sum(-1)
            else:
                box = torch.cdist(encoded[b] * weights, gt, p=1)
            matches.append(assign(self.cost_class * cls + self.cost_box * box))
        return matches


def assign(cost: Tensor) -> Match:
    """Minimum-cost one-to-one assignment of a `[Q, G]` cost matrix (NaN costs 1e6)."""
    q_idx, g_idx = linear_sum_assignment(np.nan_to_num(cost.detach().cpu().numpy(), nan=1e6))
    return Match(torch.as_tensor(q_idx, dtype=torch.long),
                 torch.as_tensor(g_idx, dtype=torch.long))


def sigmoid_focal_loss(logits: Tensor, targets: Tensor, alpha: float = 0.25,
                       gamma: float = 2.0) -> Tensor:
    """Summed sigmoid focal loss (RetinaNet) of `logits` against 0/1 `targets` (same shape)."""
    p = logits.sigmoid()
    ce = F.binary_cross_entropy_with_logits(logits, targets, reduction="none")
    p_t = p * targets + (1 - p) * (1 - targets)
    loss = ce * (1 - p_t).pow(gamma)
    loss = loss * (alpha * targets + (1 - alpha) * (1 - targets))
    return loss.sum()


def gaussian_radius(length: float, width: float, min_overlap: float = 0.1) -> float:
    """CenterNet/CenterPoint Gaussian radius (in cells) for a box `length` x `width` cells."""
    h, w = length, width
    b1 = h + w
    c1 = w * h * (1 - min_overlap) / (1 + min_overlap)
    r1 = (b1 + math.sqrt(b1 ** 2 - 4 * c1)) / 2
    b2 = 2 * (h + w)
    c2 = (1 - min_overlap) * w * h
    r2 = (b2 + math.sqrt(b2 ** 2 - 16 * c2)) / 2
    a3 = 4 * min_overlap
    b3 = -2 * min_overlap * (h + w)
    c3 = (min_overlap - 1) * w * h
    r3 = (b3 + math.sqrt(b3 ** 2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


def heatmap_target(target: Target, grid: BEVGrid, n_classes: int,
                   min_radius: int = 1) -> Tensor:
    """`[C, S, S]` Gaussian centre heatmap of one frame on `grid` (peak 1 at centre cells)."""
    heat = np.zeros((n_classes, grid.size, grid.size), dtype=np.float32)
    boxes = target.boxes.detach().cpu().numpy()
    labels = target.labels.cpu().numpy()
    for box, label in zip(boxes, labels, strict=True):
        cx = (box[0] - grid.origin) / grid.cell
        cy = (box[1] - grid.origin) / grid.cell
        ix, iy = int(math.floor(cx)), int(math.floor(cy))
        if not (0 <= ix < grid.size and 0 <= iy < grid.size):
            continue
        radius = max(min_radius, int(gaussian_radius(box[4] / grid.cell, box[3] / grid.cell)))
        sigma = (2 * radius + 1) / 6.0
        ys = np.arange(max(0, iy - radius), min(grid.size, iy + radius + 1))
        xs = np.arange(max(0, ix - radius), min(grid.size, ix + radius + 1))
        g = np.exp(-((ys[:, None] - iy) ** 2 + (xs[None, :] - ix) ** 2) / (2 * sigma ** 2))
        patch = heat[label, ys[0]:ys[-1] + 1, xs[0]:xs[-1] + 1]
        np.maximum(patch, g, out=patch)
    return torch.from_numpy(heat)


def heatmap_focal_loss(logits: Tensor, target: Tensor) -> Tensor:
    """CenterNet penalty-reduced focal loss, normalised by the number of peaks."""
    pos = target.eq(1).float()
    log_p = F.logsigmoid(logits)
    log_not_p = F.logsigmoid(-logits)
    p = log_p.exp()
    pos_loss = (log_p * (1 - p).pow(2) * pos).sum()
    neg_loss = (log_not_p * p.pow(2) * (1 - target).pow(4) * (1 - pos)).sum()
    return -(pos_loss + neg_loss) / pos.sum().clamp_min(1.0)


@dataclass(frozen=True)
class LossWeights:
    """Weights of the loss terms (DETR3D: class 2.0, box 0.25; TransFusion heatmap 1.0)."""

    cls: float = 2.0
    box: float = 0.25
    heatmap: float = 1.0


class SetCriterion:
    """Total training loss of a detector output dict (see detectors.model.detector)."""

    def __init__(self, fine_grid: BEVGrid, n_classes: int,
                 weights: LossWeights = LossWeights(),
                 matcher: HungarianMatcher | None = None,
                 class_group: tuple[int, ...] | None = None) -> None:
        self.fine_grid = fine_grid
        self.n_classes = n_classes
        self.weights = weights
        self.matcher = matcher or HungarianMatcher()
        self.class_group = None if class_group is None else \
            torch.as_tensor(class_group, dtype=torch.long)

    def __call__(self, outputs: dict[str, Tensor], targets: list[Target]) -> dict[str, Tensor]:
        """Returns `loss` (to minimise) and its parts `heatmap`, `cls`, `box` (summed over
        layers) and `cls_last`, `box_last` (final layer), all scalars. With `class_group`
        set, the boxes are `outputs["pred_group_encoded"]` (group-aware matching and loss)."""
        class_group = self.class_group
        grouped = class_group is not None
        if grouped and "pred_group_encoded" not in outputs:
            raise ValueError("class_group is set but the outputs have no pred_group_encoded "
                             "(a unified-head detector)")
        logits_all = outputs["pred_logits"]
        encoded_all = outputs["pred_group_encoded" if grouped else "pred_encoded"]
        n_layers = logits_all.shape[0]
        device = logits_all.device
        n_gt = max(1.0, float(sum(len(t.labels) for t in targets)))
        weights = torch.tensor(CODE_WEIGHTS, device=device)
        if class_group is not None:
            class_group = class_group.to(device)   # once, not per frame and layer
        heat_t = torch.stack([heatmap_target(t, self.fine_grid, self.n_classes)
                              for t in targets]).to(device)
        loss_heat = heatmap_focal_loss(outputs["heatmap"], heat_t)
        cls_terms, box_terms = [], []
        for layer in range(n_layers):
            logits, encoded = logits_all[layer], encoded_all[layer]
            matches = self.matcher(logits, encoded, targets, class_group)
            onehot = torch.zeros_like(logits)
            pred, gt = [], []
            for b, (m, t) in enumerate(zip(matches, targets, strict=True)):
                onehot[b, m.query, t.labels[m.gt]] = 1.0
                if grouped:
                    group = class_group[t.labels[m.gt]]  # type: ignore[index]
                    pred.append(encoded[b, m.query, group])
                else:
                    pred.append(encoded[b, m.query])
                gt.append(encode_boxes(t.boxes[m.gt].to(encoded)))
            cls_terms.append(sigmoid_focal_loss(logits, onehot) / n_gt)
            diff = (torch.cat(pred) - torch.cat(gt)).abs() * weights
            box_terms.append(diff.sum() / n_gt)
        loss_cls = torch.stack(cls_terms)
        loss_box = torch.stack(box_terms)
        w = self.weights
        total = w.heatmap * loss_heat + w.cls * loss_cls.sum() + w.box * loss_box.sum()
        return {"loss": total, "heatmap": loss_heat.detach(), "cls": loss_cls.sum().detach(),
                "box": loss_box.sum().detach(), "cls_last": loss_cls[-1].detach(),
                "box_last": loss_box[-1].detach()}
