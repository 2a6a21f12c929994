"""BoxeR-2D parts: output shapes, the head's offset parametrisation, box-attention's
sampling against a hand computation, eqs. 1-4, GIoU and the loss weights of Table 2."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from detectors.boxer2d import (
    BoxAttention,
    Boxer2D,
    Boxer2DConfig,
    Boxer2DCriterion,
    Boxer2DLossWeights,
    ImageTarget,
    WindowHead,
    frame_inputs,
    frame_targets,
)
from detectors.sim import CLASSES, make_image_frame


def tiny_config() -> Boxer2DConfig:
    return Boxer2DConfig(classes=tuple(CLASSES), c1=8, c2=16, d_model=16, n_heads=2,
                         d_ffn=32, n_decoder=2, n_queries=7)


def test_forward_shapes() -> None:
    torch.manual_seed(0)
    cfg = tiny_config()
    model = Boxer2D(cfg).eval()
    out = model(torch.randn(6, 4, 72, 120))
    t = (72 // 4) * (120 // 4)
    assert out["pred_logits"].shape == (2, 6, 7, len(CLASSES))
    assert out["pred_boxes"].shape == (2, 6, 7, 4)
    assert out["ref_windows"].shape == (2, 6, 7, 4)
    assert out["proposal_logits"].shape == (6, t)
    assert out["proposal_boxes"].shape == (6, t, 4)
    assert out["query_index"].shape == (6, 7)
    assert ((out["pred_boxes"] > 0) & (out["pred_boxes"] < 1)).all()
    # each layer's reference window is the previous layer's box; the first the proposal's
    assert torch.equal(out["ref_windows"][1], out["pred_boxes"][0])
    first = out["proposal_boxes"].gather(1, out["query_index"][..., None].expand(-1, -1, 4))
    assert torch.equal(out["ref_windows"][0], first)


def test_frame_inputs_scale_the_channels_and_pad_the_bottom_row() -> None:
    frame = make_image_frame(100_000)
    x = frame_inputs(frame.images, tiny_config())
    assert x.shape == (6, 4, 72, 120)
    rgb = torch.from_numpy(np.array(frame.images.rgb)).permute(0, 3, 1, 2)
    assert torch.allclose(x[:, :3, :71], rgb - 0.5)
    assert torch.allclose(x[:, 3, :71], torch.from_numpy(np.array(frame.images.depth)) / 70.0)
    assert (x[:, :, 71] == 0).all()
    targets = frame_targets(frame.truth, tiny_config())
    assert sum(len(t.labels) for t in targets) == len(frame.truth)
    cam0 = frame.truth.bbox[frame.truth.camera == 0]
    assert torch.allclose(targets[0].boxes[:, 0] * 120, torch.from_numpy(
        cam0[:, 0] + cam0[:, 2] / 2))


def test_head_starts_at_its_reference_window_and_adds_offsets_in_logit_space() -> None:
    torch.manual_seed(0)
    head = WindowHead(8, 3)
    query = torch.randn(5, 8)
    ref = torch.tensor([[0.5, 0.5, 0.1, 0.2]]).expand(5, 4)
    logits, box = head(query, ref)
    assert logits.shape == (5, 3) and torch.allclose(box, ref, atol=1e-6)
    assert torch.allclose(logits.sigmoid(), torch.tensor(0.01), atol=0.02)
    delta = torch.tensor([0.3, -0.2, 1.0, -1.0])
    with torch.no_grad():
        head.offsets[-1].bias.copy_(delta)
        _, box = head(query, ref)
    logit = torch.log(ref / (1 - ref))
    assert torch.allclose(box, torch.sigmoid(delta + logit), atol=1e-6)
    assert float(box[0, 0]) == pytest.approx(1 / (1 + math.exp(-0.3)), abs=1e-6)


def _identity_attention(d: int, n_heads: int = 1) -> BoxAttention:
    attn = BoxAttention(d, n_heads)
    with torch.no_grad():
        for lin in (attn.value_proj, attn.out_proj):
            lin.weight.copy_(torch.eye(d))
            lin.bias.zero_()
        attn.window_proj.bias.zero_()
    return attn


def _bilinear(fmap: torch.Tensor, x: float, y: float) -> torch.Tensor:
    """Hand bilinear interpolation of `fmap [D, h, w]` at normalised (x, y), zero outside."""
    d, h, w = fmap.shape
    px, py = x * w - 0.5, y * h - 0.5
    x0, y0 = math.floor(px), math.floor(py)
    out = torch.zeros(d)
    for xi, wx in ((x0, 1 - (px - x0)), (x0 + 1, px - x0)):
        for yi, wy in ((y0, 1 - (py - y0)), (y0 + 1, py - y0)):
            if 0 <= xi < w and 0 <= yi < h:
                out += wx * wy * fmap[:, yi, xi]
    return out


def test_box_attention_averages_a_bilinear_two_by_two_grid_in_the_window() -> None:
    fmap = torch.arange(2 * 3 * 4, dtype=torch.float32).view(2, 3, 4) ** 1.5
    attn = _identity_attention(2)
    window = torch.tensor([0.45, 0.5, 0.5, 0.6])          # cx cy w h (normalised)
    out = attn(torch.randn(1, 1, 2), window.view(1, 1, 4), fmap[None])
    points = [(0.45 + gx * 0.5, 0.5 + gy * 0.6) for gy in (-0.25, 0.25) for gx in (-0.25, 0.25)]
    assert points[0] == (0.325, 0.35)
    expected = sum(_bilinear(fmap, x, y) for x, y in points) / 4
    assert torch.allclose(out[0, 0], expected, atol=1e-5)


def test_box_attention_moves_and_enlarges_each_heads_window_by_eqs_1_to_4() -> None:
    attn = _identity_attention(4, n_heads=2)
    with torch.no_grad():
        attn.window_proj.bias.copy_(torch.tensor([1.0, -2.0, 3.0, -1.0,   # head 0
                                                  0.0, 0.0, -5.0, 8.0]))  # head 1
    window = torch.tensor([[[0.5, 0.4, 0.2, 0.16]]])
    heads = attn.head_windows(torch.zeros(1, 1, 4), window)[0, 0].detach()
    tau = 8.0
    assert torch.allclose(heads[0], torch.tensor([0.5 + 1 * 0.2 / tau, 0.4 - 2 * 0.16 / tau,
                                                  0.2 + 3 * 0.2 / tau, 0.16]))
    assert torch.allclose(heads[1], torch.tensor([0.5, 0.4, 0.2, 0.16 + 8 * 0.16 / tau]))
    # the two heads read their own channels from their own windows
    fmap = torch.rand(4, 5, 6)
    out = attn(torch.zeros(1, 1, 4), window, fmap[None])[0, 0].detach()
    for h in range(2):
        pts = attn.sample_points(heads[h])
        exp = sum(_bilinear(fmap[2 * h:2 * h + 2], float(x), float(y)) for x, y in pts) / 4
        assert torch.allclose(out[2 * h:2 * h + 2], exp, atol=1e-5)


def test_loss_weights_are_table_2_and_perfect_boxes_cost_no_box_loss() -> None:
    w = Boxer2DLossWeights()
    assert (w.cls, w.l1, w.giou) == (2.0, 5.0, 2.0)
    torch.manual_seed(0)
    cfg = tiny_config()
    out = Boxer2D(cfg)(torch.randn(2, 4, 72, 120))
    targets = [ImageTarget(torch.tensor([0, 5]), torch.tensor([[0.3, 0.4, 0.1, 0.2],
                                                               [0.7, 0.5, 0.05, 0.1]])),
               ImageTarget(torch.zeros(0, dtype=torch.long), torch.zeros(0, 4))]
    losses = Boxer2DCriterion()(out, targets)
    total = losses["enc"] + 2 * losses["cls"] + 5 * losses["l1"] + 2 * losses["giou"]
    assert torch.allclose(losses["loss"], total, rtol=1e-5)
    losses["loss"].backward()
    # put the last layer's boxes exactly on the ground truth of its matched queries
    crit = Boxer2DCriterion()
    logits, boxes = out["pred_logits"][-1].detach(), out["pred_boxes"][-1].detach().clone()
    match = crit.match(logits, boxes, targets)[0]
    boxes[0, match.query] = targets[0].boxes[match.gt]
    _, l1, giou = crit.stage(logits, boxes, targets, 2.0)
    assert float(l1) == pytest.approx(0.0, abs=1e-6) and float(giou) == pytest.approx(0.0,
                                                                                       abs=1e-6)
