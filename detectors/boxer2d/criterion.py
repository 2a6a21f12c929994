"""BoxeR-2D's training loss: Hungarian matching, sigmoid focal, L1 and GIoU (Table 2).

Every decoder layer's queries, and the proposal stage's tokens (one foreground class), are
matched to the ground truth of their image independently (`detectors.losses.assign`) on

    cost = 2 * focal_cost(class) + 5 * L1(cx cy w h) - 2 * GIoU

the loss weights of Table 2 (focal 2, L1 5, GIoU 2), also the matcher's as in Deformable
DETR. The focal loss covers every query (unmatched ones learn all-zero targets), L1 and GIoU
the matched ones; each term is normalised by the number of ground-truth boxes in the batch,
and the layers and the proposal stage are summed.

Targets: one `ImageTarget(labels [G] int64, boxes [G, 4] cx cy w h in [0, 1])` per image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from detectors.boxer2d.boxes import cxcywh_to_xyxy, generalized_iou
from detectors.losses import Match, assign, focal_cost, sigmoid_focal_loss


class ImageTarget(NamedTuple):
    """Ground truth of one image: `labels [G]` int64, `boxes [G, 4]` cx cy w h in [0, 1]."""

    labels: Tensor
    boxes: Tensor


@dataclass(frozen=True)
class Boxer2DLossWeights:
    """Table 2 of seed 004: focal 2, L1 5, GIoU 2 (matching and loss)."""

    cls: float = 2.0
    l1: float = 5.0
    giou: float = 2.0


LOG_TERMS = ("loss", "cls", "l1", "giou", "enc", "cls_last", "l1_last", "giou_last")


class Boxer2DCriterion:
    """Total loss of a `Boxer2D` output dict; see the module docstring."""

    def __init__(self, weights: Boxer2DLossWeights = Boxer2DLossWeights()) -> None:
        self.weights = weights

    @torch.no_grad()
    def match(self, logits: Tensor, boxes: Tensor, targets: list[ImageTarget]) -> list[Match]:
        """`logits [N, Q, C]`, `boxes [N, Q, 4]` -> N matches (query, ground truth)."""
        w = self.weights
        out = []
        for b, t in enumerate(targets):
            if len(t.labels) == 0:
                empty = torch.zeros(0, dtype=torch.long)
                out.append(Match(empty, empty))
                continue
            cost = (w.cls * focal_cost(logits[b])[:, t.labels]
                    + w.l1 * torch.cdist(boxes[b], t.boxes, p=1)
                    - w.giou * generalized_iou(cxcywh_to_xyxy(boxes[b]),
                                               cxcywh_to_xyxy(t.boxes)))
            out.append(assign(cost))
        return out

    def stage(self, logits: Tensor, boxes: Tensor, targets: list[ImageTarget],
              n_gt: float) -> tuple[Tensor, Tensor, Tensor]:
        """(focal, L1, GIoU) losses of one stage, `logits [N, Q, C]`, `boxes [N, Q, 4]`."""
        matches = self.match(logits, boxes, targets)
        onehot = torch.zeros_like(logits)
        pred, gt = [], []
        for b, (m, t) in enumerate(zip(matches, targets, strict=True)):
            onehot[b, m.query, t.labels[m.gt]] = 1.0
            pred.append(boxes[b, m.query])
            gt.append(t.boxes[m.gt])
        p, g = torch.cat(pred), torch.cat(gt)
        l1 = (p - g).abs().sum() / n_gt
        giou = (1 - generalized_iou(cxcywh_to_xyxy(p), cxcywh_to_xyxy(g)).diagonal()).sum() \
            / n_gt
        return sigmoid_focal_loss(logits, onehot) / n_gt, l1, giou

    def __call__(self, outputs: dict[str, Tensor], targets: list[ImageTarget]
                 ) -> dict[str, Tensor]:
        """`loss` (to minimise) and its parts (`LOG_TERMS`): `cls`, `l1`, `giou` summed over
        the decoder layers, `enc` the weighted proposal-stage loss, `*_last` the last layer."""
        w = self.weights
        n_gt = max(1.0, float(sum(len(t.labels) for t in targets)))
        binary = [ImageTarget(torch.zeros_like(t.labels), t.boxes) for t in targets]
        enc = self.stage(outputs["proposal_logits"][..., None], outputs["proposal_boxes"],
                         binary, n_gt)
        enc_loss = w.cls * enc[0] + w.l1 * enc[1] + w.giou * enc[2]
        layers = [self.stage(lg, bx, targets, n_gt)
                  for lg, bx in zip(outputs["pred_logits"], outputs["pred_boxes"], strict=True)]
        cls, l1, giou = (torch.stack(terms) for terms in zip(*layers, strict=True))
        total = enc_loss + w.cls * cls.sum() + w.l1 * l1.sum() + w.giou * giou.sum()
        return {"loss": total, "cls": cls.sum().detach(), "l1": l1.sum().detach(),
                "giou": giou.sum().detach(), "enc": enc_loss.detach(),
                "cls_last": cls[-1].detach(), "l1_last": l1[-1].detach(),
                "giou_last": giou[-1].detach()}
