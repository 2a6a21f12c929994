"""Group regression heads (seed 001): shapes, option-A refinement, group-aware matching and
loss, fine-resolution tokens, fade-out of object sampling, hypotheses in dumps."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from detectors.losses import HungarianMatcher, SetCriterion, Target
from detectors.model import Detector, DetectorConfig, encode_boxes
from detectors.model.groups import DEFAULT_GROUPS, class_groups, group_scores
from detectors.samples import TrainSamples, frame_sample
from detectors.sim import CLASSES, SPLITS, make_frame
from detectors.train import TrainConfig

GROUP_OF = class_groups(CLASSES, DEFAULT_GROUPS)


@pytest.fixture(scope="module")
def frames() -> list:
    return [make_frame(seed, "lidar") for seed in (3, 4)]


def _points(frames: list) -> list[torch.Tensor]:
    return [torch.from_numpy(np.array(f.sensor_frame.points, dtype=np.float32)) for f in frames]


def test_groups_cover_every_class_once() -> None:
    assert len(DEFAULT_GROUPS) == 6
    assert GROUP_OF[CLASSES.index("car")] == 0
    assert GROUP_OF[CLASSES.index("bus")] == GROUP_OF[CLASSES.index("trailer")]
    assert GROUP_OF[CLASSES.index("pedestrian")] == GROUP_OF[CLASSES.index("traffic_cone")]
    with pytest.raises(ValueError, match="no group"):
        class_groups(CLASSES, DEFAULT_GROUPS[:-1])
    with pytest.raises(ValueError, match="head"):
        DetectorConfig(sensor="lidar", features=("x",), classes=CLASSES, head="grouped")
    with pytest.raises(ValueError, match="token_stride"):
        DetectorConfig(sensor="lidar", features=("x",), classes=CLASSES, token_stride=3)


def test_group_outputs_have_the_documented_shapes(frames: list, tiny_config) -> None:
    torch.manual_seed(0)
    cfg = tiny_config(head="group")
    model = Detector(cfg).eval()
    with torch.no_grad():
        out = model(_points(frames))
    n_l, b, q, c, g = cfg.n_layers, 2, cfg.n_queries, len(CLASSES), 6
    assert out["pred_logits"].shape == (n_l, b, q, c)
    assert out["pred_group_boxes"].shape == (n_l, b, q, g, 9)
    assert out["pred_group_encoded"].shape == (n_l, b, q, g, 10)
    assert out["group_scores"].shape == (n_l, b, q, g)
    assert out["pred_boxes"].shape == (n_l, b, q, 9)
    assert out["attention"].shape == (n_l, b, q, 16 * 16)
    # group score = summed class probabilities of the group
    want = group_scores(out["pred_logits"], torch.tensor(GROUP_OF), g)
    assert torch.allclose(out["group_scores"], want)
    assert torch.allclose(out["group_scores"].sum(-1), out["pred_logits"].sigmoid().sum(-1),
                          atol=1e-5)
    # a query's box is its top class's group's box, at every layer
    top = torch.tensor(GROUP_OF)[out["pred_logits"].argmax(-1)]
    picked = out["pred_group_boxes"].gather(
        3, top[..., None, None].expand(-1, -1, -1, 1, 9)).squeeze(3)
    assert torch.allclose(out["pred_boxes"], picked)


def test_option_a_moves_anchors_to_the_score_weighted_mean(frames: list, tiny_config) -> None:
    torch.manual_seed(1)
    model = Detector(tiny_config(head="group")).eval()
    # give the group heads distinct centre offsets so the mean is not any single head's
    with torch.no_grad():
        for head in model.heads:
            for g, box in enumerate(head.boxes):
                box[-1].bias[0:2] = torch.tensor([g - 2.5, 0.5 * g])
        out = model(_points(frames))
    centres = out["pred_group_boxes"][0, ..., 0:2].double()  # [B, Q, G, 2], layer 0
    w = out["group_scores"][0].double()
    mean = (w[..., None] * centres).sum(-2) / w.sum(-1, keepdim=True)
    assert torch.allclose(out["anchors"][1].double(), mean, atol=1e-4)
    # and it is not simply the top group's centre
    assert not torch.allclose(out["anchors"][1], out["pred_boxes"][0, ..., 0:2], atol=1e-2)


def test_unified_head_is_still_the_default(frames: list, tiny_config) -> None:
    cfg = tiny_config()
    assert cfg.head == "unified" and cfg.token_stride == 4
    old = cfg.to_dict()
    for key in ("head", "groups", "token_stride"):  # a v1 weights file's config
        old.pop(key)
    assert DetectorConfig.from_dict(old) == cfg
    model = Detector(cfg).eval()
    with torch.no_grad():
        out = model(_points(frames[:1]))
    assert "pred_group_boxes" not in out and "group_scores" not in out
    assert torch.allclose(out["anchors"][1], out["pred_boxes"][0, ..., :2])


def _group_encoded(q: int, where: dict[tuple[int, int], tuple[float, float]]) -> torch.Tensor:
    """`[1, q, 6, 10]` boxes 50 m away, except (query, group) -> (x, y) in `where`."""
    box = torch.tensor([50.0, 50.0, 0.0, 2.0, 4.0, 1.5, 0.0, 0.0, 0.0])
    boxes = box.repeat(q, 6, 1)
    for (i, g), xy in where.items():
        boxes[i, g, 0:2] = torch.tensor(xy)
    return encode_boxes(boxes)[None]


def test_matcher_compares_a_ground_truth_with_its_own_groups_box() -> None:
    car, ped = CLASSES.index("car"), CLASSES.index("pedestrian")
    g_car, g_ped = GROUP_OF[car], GROUP_OF[ped]
    gt = torch.tensor([[0.0, 0.0, 0.0, 2.0, 4.0, 1.5, 0.0, 0.0, 0.0]])
    # query 0: its pedestrian head sits exactly on the car, its car head is far away;
    # query 1: its car head is 1 m off the car
    encoded = _group_encoded(2, {(0, g_ped): (0.0, 0.0), (1, g_car): (1.0, 0.0)})
    logits = torch.zeros(1, 2, len(CLASSES))
    matcher = HungarianMatcher()
    (m,) = matcher(logits, encoded, [Target(torch.tensor([car]), gt)],
                   class_group=torch.tensor(GROUP_OF))
    assert m.query.tolist() == [1]
    (m,) = matcher(logits, encoded, [Target(torch.tensor([ped]), gt)],
                   class_group=torch.tensor(GROUP_OF))
    assert m.query.tolist() == [0]


def test_box_loss_reaches_only_the_matched_groups_head(tiny_config) -> None:
    bus = CLASSES.index("bus")
    g_bus = GROUP_OF[bus]
    gt = torch.tensor([[3.0, 1.0, 0.0, 2.5, 11.0, 3.2, 0.0, 0.0, 0.0]])
    encoded = _group_encoded(3, {(2, g_bus): (2.0, 1.0)})[None].repeat(2, 1, 1, 1, 1)
    encoded.requires_grad_(True)  # [L = 2, B = 1, Q = 3, G = 6, 10]
    logits = torch.zeros(2, 1, 3, len(CLASSES), requires_grad=True)
    model = Detector(tiny_config(head="group"))
    criterion = SetCriterion(model.fine_grid, len(CLASSES), class_group=model.class_group)
    outputs = {"pred_logits": logits, "pred_group_encoded": encoded,
               "pred_encoded": encoded[..., 0, :],
               "heatmap": torch.zeros(1, len(CLASSES), 32, 32)}
    losses = criterion(outputs, [Target(torch.tensor([bus]), gt)])
    losses["loss"].backward()
    grad = encoded.grad.abs().sum(-1)  # [L, 1, Q, G]
    assert grad[:, 0, 2, g_bus].gt(0).all()
    grad[:, 0, 2, g_bus] = 0
    assert grad.eq(0).all()
    with pytest.raises(ValueError, match="pred_group_encoded"):
        criterion({k: v for k, v in outputs.items() if k != "pred_group_encoded"},
                  [Target(torch.tensor([bus]), gt)])


@pytest.mark.parametrize("stride", [2, 1])
def test_group_loss_goes_down_with_fine_tokens(frames: list, tiny_config, stride: int) -> None:
    torch.manual_seed(0)
    torch.set_num_threads(1)
    cfg = tiny_config(head="group", token_stride=stride)
    model = Detector(cfg).train()
    assert model.token_centres.shape == ((64 // stride) ** 2, 2)
    samples = [frame_sample(f, model.grid.half_extent) for f in frames]
    criterion = SetCriterion(model.fine_grid, len(CLASSES), class_group=model.class_group)
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    losses = []
    for _ in range(12):
        out = model([s.points for s in samples], need_attention=False)
        assert "attention" not in out
        loss = criterion(out, [s.target for s in samples])
        opt.zero_grad()
        loss["loss"].backward()
        opt.step()
        losses.append(float(loss["loss"].detach()))
    assert all(math.isfinite(v) for v in losses)
    assert np.mean(losses[-3:]) < 0.7 * np.mean(losses[:3])


def test_object_sampling_fades_out_for_the_last_steps() -> None:
    cfg = TrainConfig.for_sensor("lidar", steps=80, extra_fade=0.25)
    assert cfg.fade_step == 60
    assert TrainConfig.for_sensor("lidar", steps=80, extra_fade=0.0).fade_step == 80
    with pytest.raises(ValueError, match="extra_fade"):
        TrainConfig.for_sensor("lidar", extra_fade=1.5)
    extra = {"bus": 3.0}
    data = TrainSamples("lidar", SPLITS["train"][:10], ("x", "y", "z"), 51.2,
                        extra_objects=extra, extra_until=8)
    assert data.extra_for(7) == extra and data.extra_for(8) is None


def test_dump_carries_the_hypotheses(tiny_config) -> None:
    from calibrators.io import load_dump, save_dump
    from detectors.dumpwriter import build_dump

    torch.manual_seed(0)
    model = Detector(tiny_config(head="group", n_queries=12)).eval()
    dump = build_dump(model, [3], cov_source="none")
    n = dump.n_detections
    assert dump.det_hyp_boxes.shape == (n, 6, 9) and dump.det_hyp_scores.shape == (n, 6)
    top = np.asarray(GROUP_OF)[dump.det_labels]
    np.testing.assert_allclose(dump.det_hyp_boxes[np.arange(n), top], dump.final_boxes,
                               atol=1e-5)
    import io

    buf = io.BytesIO()
    save_dump(buf, dump)
    buf.seek(0)
    back = load_dump(buf)
    np.testing.assert_array_equal(back.det_hyp_boxes, dump.det_hyp_boxes)
    np.testing.assert_array_equal(back.det_hyp_scores, dump.det_hyp_scores)
    unified = build_dump(Detector(tiny_config(n_queries=12)).eval(), [3], cov_source="none")
    assert unified.det_hyp_boxes is None and unified.n_hypotheses == 0


def test_a_checkpoint_of_another_architecture_is_refused(tmp_path, tiny_config) -> None:
    from detectors.train import train

    cfg = TrainConfig.for_sensor("lidar", steps=2, batch_size=1, warmup=1, ckpt_every=1,
                                 workers=0, threads=1)
    train(cfg, run_dir=tmp_path, weights_out=tmp_path / "u.pt", progress=False,
          model_config=tiny_config())
    longer = TrainConfig.for_sensor("lidar", steps=3, batch_size=1, warmup=1, ckpt_every=1,
                                    workers=0, threads=1)
    with pytest.raises(ValueError, match="architecture"):
        train(longer, run_dir=tmp_path, weights_out=tmp_path / "g.pt", progress=False,
              model_config=tiny_config(head="group"))


def test_a_v1_weights_file_loads_unified_with_the_same_outputs(frames, tmp_path,
                                                               tiny_config) -> None:
    import json

    from detectors.registry import load_weights, save_weights

    torch.manual_seed(0)
    model = Detector(tiny_config()).eval()
    path = save_weights(model, tmp_path / "v1.pt")
    payload = torch.load(path, weights_only=True)
    config = json.loads(payload["config"])
    for key in ("head", "groups", "token_stride"):   # what a v1 file's config lacks
        config.pop(key)
    payload["config"] = json.dumps(config)
    torch.save(payload, path)
    loaded, _ = load_weights(path)
    assert loaded.config.head == "unified" and loaded.config.token_stride == 4
    with torch.no_grad():
        a, b = model(_points(frames)), loaded(_points(frames))
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key
