"""Box geometry of the image-plane detector: normalised `cx cy w h` windows, COCO `x y w h`
pixels, generalised IoU, inverse sigmoid and the sinusoidal window encoding.

Windows and predicted boxes are `[..., 4]` = `cx cy w h` in [0, 1], normalised by the
(padded) input size `width x height` (`Boxer2DConfig.input_size`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def cxcywh_to_xyxy(box: Tensor) -> Tensor:
    """`[..., 4]` cx cy w h -> `[..., 4]` x0 y0 x1 y1."""
    cx, cy, w, h = box.unbind(-1)
    return torch.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], dim=-1)


def coco_to_cxcywh(box: Tensor, width: float, height: float) -> Tensor:
    """COCO `[..., 4]` x y w h pixels -> normalised cx cy w h."""
    x, y, w, h = box.unbind(-1)
    return torch.stack([(x + w / 2) / width, (y + h / 2) / height, w / width, h / height], -1)


def cxcywh_to_coco(box: Tensor, width: float, height: float,
                   clip: tuple[float, float] | None = None) -> Tensor:
    """Normalised `[..., 4]` cx cy w h -> COCO x y w h pixels, clipped to the image
    `clip = (W, H)` when given."""
    x0, y0, x1, y1 = cxcywh_to_xyxy(box).unbind(-1)
    x0, x1, y0, y1 = x0 * width, x1 * width, y0 * height, y1 * height
    if clip is not None:
        x0, x1 = x0.clamp(0, clip[0]), x1.clamp(0, clip[0])
        y0, y1 = y0.clamp(0, clip[1]), y1.clamp(0, clip[1])
    return torch.stack([x0, y0, x1 - x0, y1 - y0], dim=-1)


def generalized_iou(a: Tensor, b: Tensor) -> Tensor:
    """Pairwise GIoU of `a [N, 4]` and `b [M, 4]` x0 y0 x1 y1 boxes -> `[N, M]`."""
    area_a = (a[:, 2] - a[:, 0]).clamp_min(0) * (a[:, 3] - a[:, 1]).clamp_min(0)
    area_b = (b[:, 2] - b[:, 0]).clamp_min(0) * (b[:, 3] - b[:, 1]).clamp_min(0)
    lo = torch.maximum(a[:, None, :2], b[None, :, :2])
    hi = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (hi - lo).clamp_min(0).prod(-1)
    union = area_a[:, None] + area_b[None] - inter
    iou = inter / union.clamp_min(1e-9)
    lo_c = torch.minimum(a[:, None, :2], b[None, :, :2])
    hi_c = torch.maximum(a[:, None, 2:], b[None, :, 2:])
    hull = (hi_c - lo_c).clamp_min(0).prod(-1)
    return iou - (hull - union) / hull.clamp_min(1e-9)


def inverse_sigmoid(x: Tensor, eps: float = 1e-5) -> Tensor:
    """sigma^-1(x) = log(x / (1 - x)), with x clamped to [eps, 1 - eps]."""
    x = x.clamp(eps, 1 - eps)
    return torch.log(x / (1 - x))


def sine_encoding(window: Tensor, d_model: int, temperature: float = 10_000.0) -> Tensor:
    """BoxeR's spatial encoding of `[..., 4]` windows -> `[..., d_model]`: the sinusoidal
    encoding of (cx, cy) (d/2 channels each, concatenated) plus that of (w, h)."""
    n = d_model // 4
    freq = temperature ** (torch.arange(n, device=window.device, dtype=window.dtype) / n)
    angles = window[..., None] * (2 * math.pi) / freq             # [..., 4, n]
    enc = torch.cat([angles.sin(), angles.cos()], dim=-1)         # [..., 4, d/2]
    pos = torch.cat([enc[..., 0, :], enc[..., 1, :]], dim=-1)
    size = torch.cat([enc[..., 2, :], enc[..., 3, :]], dim=-1)
    return pos + size
