"""Detector output shapes, box coding, matching, and a tiny training run whose loss drops."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from detectors.losses import HungarianMatcher, SetCriterion, Target, heatmap_target
from detectors.model import Detector, decode_boxes, encode_boxes
from detectors.samples import augment, frame_sample
from detectors.sim import CLASSES, FEATURES, make_frame


@pytest.fixture(scope="module")
def frames() -> list:
    return [make_frame(seed, "lidar") for seed in (3, 4)]


def test_forward_returns_every_documented_shape(frames: list, tiny_config) -> None:
    torch.manual_seed(0)
    cfg = tiny_config()
    model = Detector(cfg).eval()
    points = [torch.from_numpy(np.array(f.sensor_frame.points, dtype=np.float32))
              for f in frames]
    with torch.no_grad():
        out = model(points)
    n_l, b, q, c, t = cfg.n_layers, 2, cfg.n_queries, len(CLASSES), 16 * 16
    assert out["pred_logits"].shape == (n_l, b, q, c)
    assert out["pred_boxes"].shape == (n_l, b, q, 9)
    assert out["pred_encoded"].shape == (n_l, b, q, 10)
    assert out["attention"].shape == (n_l, b, q, t)
    assert out["anchors"].shape == (n_l, b, q, 2)
    assert out["heatmap"].shape == (b, c, 32, 32)
    assert out["query_labels"].shape == (b, q)
    assert out["token_centres"].shape == (t, 2)
    # attention rows are distributions over the tokens; sizes are positive
    assert torch.allclose(out["attention"].sum(-1), torch.ones(n_l, b, q), atol=1e-5)
    assert (out["pred_boxes"][..., 3:6] > 0).all()
    # each layer's anchors are the previous layer's centres
    assert torch.allclose(out["anchors"][1], out["pred_boxes"][0, ..., :2])
    assert model.token_grid.cell == pytest.approx(6.4)
    assert model.token_grid.origin == pytest.approx(-51.2)


def test_box_coding_round_trips() -> None:
    boxes = torch.tensor([[10.0, -3.0, 0.5, 1.9, 4.6, 1.7, 2.5, 3.0, -1.0],
                          [-40.0, 22.0, -0.2, 0.6, 0.7, 1.8, -math.pi + 0.1, 0.0, 0.0]])
    assert torch.allclose(decode_boxes(encode_boxes(boxes)), boxes, atol=1e-5)


def test_matcher_pairs_queries_with_their_nearest_objects() -> None:
    gt = torch.tensor([[0.0, 0.0, 0, 2, 4, 1.5, 0, 0, 0], [20.0, 5.0, 0, 2, 4, 1.5, 0, 0, 0]])
    target = Target(torch.tensor([0, 5]), gt)
    pred = gt[[1, 0, 0]].clone()
    pred[2, :2] += 30.0  # a third query far from both
    logits = torch.full((1, 3, len(CLASSES)), -3.0)
    (match,) = HungarianMatcher()(logits, encode_boxes(pred)[None], [target])
    assert dict(zip(match.gt.tolist(), match.query.tolist(), strict=True)) == {0: 1, 1: 0}


def test_heatmap_target_peaks_at_object_centres(tiny_config) -> None:
    cfg = tiny_config()
    grid = Detector(cfg).fine_grid
    boxes = torch.tensor([[4.0, -8.0, 0, 1.9, 4.6, 1.7, 0, 0, 0]])
    heat = heatmap_target(Target(torch.tensor([2]), boxes), grid, len(CLASSES))
    assert heat.max() == 1.0
    c, row, col = np.unravel_index(int(heat.argmax()), heat.shape)
    assert c == 2
    assert grid.origin + (col + 0.5) * grid.cell == pytest.approx(4.0, abs=grid.cell)
    assert grid.origin + (row + 0.5) * grid.cell == pytest.approx(-8.0, abs=grid.cell)


def test_augmentation_moves_points_and_boxes_together(frames: list) -> None:
    sample = frame_sample(frames[0], 51.2)
    out = augment(sample, FEATURES["lidar"], np.random.default_rng(1))
    # distances from the ego scale by one common factor for points and box centres
    r_pts = out.points[:, :2].norm(dim=1) / sample.points[:, :2].norm(dim=1).clamp_min(1e-6)
    r_box = out.target.boxes[:, :2].norm(dim=1) / sample.target.boxes[:, :2].norm(dim=1)
    assert torch.allclose(r_pts[sample.points[:, :2].norm(dim=1) > 1], r_pts.median(), atol=1e-4)
    assert torch.allclose(r_box, r_pts.median(), atol=1e-4)
    assert torch.equal(out.target.labels, sample.target.labels)


def test_loss_goes_down_on_fixed_frames(frames: list, tiny_config) -> None:
    torch.manual_seed(0)
    torch.set_num_threads(1)
    cfg = tiny_config()
    model = Detector(cfg).train()
    samples = [frame_sample(f, model.grid.half_extent) for f in frames]
    criterion = SetCriterion(model.fine_grid, len(CLASSES))
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(12):
        out = model([s.points for s in samples])
        loss = criterion(out, [s.target for s in samples])
        opt.zero_grad()
        loss["loss"].backward()
        opt.step()
        losses.append(float(loss["loss"].detach()))
    assert all(math.isfinite(v) for v in losses)
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])


def test_mc_dropout_samples_differ_while_batchnorm_stays_frozen(frames: list,
                                                                tiny_config) -> None:
    from detectors.infer import enable_mc_dropout

    torch.manual_seed(0)
    model = enable_mc_dropout(Detector(tiny_config(dropout=0.2)))
    assert not model.backbone.training and model.layers[0].ffn[2].training
    points = [torch.from_numpy(np.array(frames[0].sensor_frame.points, dtype=np.float32))]
    with torch.no_grad():
        a, b = model(points), model(points)
    assert torch.equal(a["heatmap"], b["heatmap"])  # the backbone is deterministic
    assert not torch.equal(a["pred_logits"], b["pred_logits"])  # the decoder samples
