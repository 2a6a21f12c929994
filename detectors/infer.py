"""Inference: run a detector over point clouds and keep the per-query outputs that matter.

Three decodings (`DECODINGS`):

- "topk_nms" (the default): "topk", then class-wise circle NMS on the box centres with
  CenterPoint's radii (`detectors.nms`): a second query on an object already detected with
  the same class is dropped, so at most `max_detections` remain;
- "topk" (DETR3D's and PETR's NMS-free coder): the `max_detections` (query, class) pairs
  with the highest final-layer sigmoid probability over all Q x C pairs; a query whose best
  class is a look-alike (trailer for a bus) also gives its second class as a detection of
  its own, with the same logits and boxes;
- "query": one detection per query, its arg-max class; the `max_detections` queries with
  the highest score are kept.

Either way each detection keeps its query's outputs from every decoder layer.

Per frame (K kept queries, L layers, C classes, T tokens):

    FrameDetections(layer_logits [K, L, C], layer_boxes [K, L, 9], attention [K, T] (final
                    layer), scores [K], labels [K] (the class each detection asserts),
                    query_index [K] (repeats under "topk"),
                    hyp_boxes [K, G, 9] | None, hyp_scores [K, G] | None)

`hyp_boxes` / `hyp_scores` (group regression heads only, else None): the final layer's box
of every group head and its group score (summed class probabilities of the group), the
multi-hypothesis output of seed 001.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from detectors.model.detector import Detector
from detectors.nms import circle_nms, class_radii_sq
from detectors.vocab import DECODINGS


@dataclass(frozen=True)
class FrameDetections:
    """The kept queries of one frame (shapes in the module docstring), sorted by score."""

    layer_logits: Tensor
    layer_boxes: Tensor
    attention: Tensor
    scores: Tensor
    labels: Tensor
    query_index: Tensor
    hyp_boxes: Tensor | None = None
    hyp_scores: Tensor | None = None

    @property
    def boxes(self) -> Tensor:
        """`[K, 9]` final-layer boxes."""
        return self.layer_boxes[:, -1]


def enable_mc_dropout(model: nn.Module) -> nn.Module:
    """Put only the dropout-carrying modules (Dropout, MultiheadAttention) in train mode, so
    repeated forward passes sample MC-dropout outputs; BatchNorm stays in eval mode."""
    model.eval()
    for module in model.modules():
        if isinstance(module, nn.Dropout | nn.MultiheadAttention):
            module.train()
    return model


def postprocess(outputs: dict[str, Tensor], max_detections: int = 100,
                decode: str = "topk", classes: Sequence[str] | None = None
                ) -> list[FrameDetections]:
    """Split a detector output dict into per-frame detections (`decode`: module docstring;
    "topk_nms" needs the detector's `classes`, for their NMS radii)."""
    if decode not in DECODINGS:
        raise ValueError(f"decode must be one of {list(DECODINGS)}, got {decode!r}")
    radii_sq = None
    if decode == "topk_nms":
        if classes is None:
            raise ValueError("decode 'topk_nms' needs the detector's classes (NMS radii)")
        radii_sq = class_radii_sq(classes)
    logits = outputs["pred_logits"]  # [L, B, Q, C]
    boxes = outputs["pred_boxes"]  # [L, B, Q, 9]
    attention = outputs["attention"]  # [L, B, Q, T]
    hyp_boxes = outputs.get("pred_group_boxes")  # [L, B, Q, G, 9] (group heads)
    hyp_scores = outputs.get("group_scores")  # [L, B, Q, G]
    n_layers, batch, n_queries, n_classes = logits.shape
    frames = []
    for b in range(batch):
        final = logits[-1, b].sigmoid()  # [Q, C]
        if decode in ("topk", "topk_nms"):
            scores, pair = final.reshape(-1).topk(min(max_detections, final.numel()))
            order, labels = pair // n_classes, pair % n_classes
            if radii_sq is not None:
                keep = circle_nms(boxes[-1, b, order, :2], labels, scores, radii_sq)
                scores, order, labels = scores[keep], order[keep], labels[keep]
        else:
            best, labels = final.max(dim=1)
            scores, order = best.topk(min(max_detections, n_queries))
            labels = labels[order]
        frames.append(FrameDetections(
            layer_logits=logits[:, b, order].transpose(0, 1).contiguous(),
            layer_boxes=boxes[:, b, order].transpose(0, 1).contiguous(),
            attention=attention[-1, b, order].contiguous(),
            scores=scores, labels=labels, query_index=order,
            hyp_boxes=None if hyp_boxes is None else hyp_boxes[-1, b, order].contiguous(),
            hyp_scores=None if hyp_scores is None else hyp_scores[-1, b, order].contiguous()))
    return frames


@torch.no_grad()
def detect(model: Detector, points: Iterable[Tensor], batch_size: int = 1,
           max_detections: int = 100, decode: str = DECODINGS[0]
           ) -> Iterator[FrameDetections]:
    """Run `model` (in whatever mode it is in) over point clouds `[P, F]`, frame by frame."""
    classes = model.config.classes
    batch: list[Tensor] = []
    for p in points:
        batch.append(torch.as_tensor(p, dtype=torch.float32))
        if len(batch) == batch_size:
            yield from postprocess(model(batch), max_detections, decode, classes)
            batch = []
    if batch:
        yield from postprocess(model(batch), max_detections, decode, classes)
