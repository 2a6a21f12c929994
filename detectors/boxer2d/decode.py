"""Detections of one image from a `Boxer2D` output: the best (query, class) pairs.

As Deformable DETR's post-processing (no NMS): the sigmoid scores of the last decoder layer,
`[K, C]`, flattened; the `max_dets` highest become detections, a query may give several
classes. Each keeps the query's evidence for calibration: its last-layer logits `[C]`, every
layer's logits `[L, C]` and every layer's box `[L, 4]` (the decoder-layer spread).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from detectors.boxer2d.boxes import cxcywh_to_coco
from detectors.boxer2d.config import Boxer2DConfig


def decode_image(outputs: dict[str, Tensor], image: int, config: Boxer2DConfig,
                 max_dets: int = 100) -> list[dict[str, Any]]:
    """Detections of image `image` (index into N) of `outputs` (`Boxer2D.forward`), best
    first: dicts with `category_id` (class index + 1), `bbox` COCO x y w h pixels clipped to
    the image, `score`, `logits [C]`, `layer_logits [L, C]`, `layer_boxes [L, 4]` (lists),
    and `query` (index into K)."""
    logits = outputs["pred_logits"][:, image].detach()                        # [L, K, C]
    boxes = outputs["pred_boxes"][:, image].detach()                          # [L, K, 4]
    n_classes = logits.shape[-1]
    scores = logits[-1].sigmoid().flatten()
    top = scores.topk(min(max_dets, scores.numel()))
    query = torch.div(top.indices, n_classes, rounding_mode="floor")
    label = top.indices % n_classes
    w_in, h_in = config.input_size
    pixels = cxcywh_to_coco(boxes[:, query], w_in, h_in, clip=config.image_size)  # [L, M, 4]
    dets = []
    for j in range(len(query)):
        q = int(query[j])
        dets.append({
            "category_id": int(label[j]) + 1,
            "bbox": _round(pixels[-1, j]),
            "score": round(float(top.values[j]), 6),
            "logits": _round(logits[-1, q]),
            "layer_logits": [_round(row) for row in logits[:, q]],
            "layer_boxes": [_round(row) for row in pixels[:, j]],
            "query": q,
        })
    return dets


def _round(values: Tensor, digits: int = 4) -> list[float]:
    return [round(float(v), digits) for v in values]
