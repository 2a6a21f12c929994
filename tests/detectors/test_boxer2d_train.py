"""BoxeR-2D training is deterministic and resumes exactly; the shipped weights load and
detect; the COCO dump holds the calibration fields and pycocotools reads it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from detectors.boxer2d import (
    WEIGHTS_FILE,
    Boxer2DTrainConfig,
    build_boxer2d,
    coco_ap,
    dump_coco,
    frame_inputs,
    load_boxer2d,
    train_boxer2d,
)
from detectors.boxer2d.boxes import generalized_iou
from detectors.sim import CLASSES, make_image_frame
from tests.detectors.test_boxer2d_model import tiny_config


def _cfg() -> Boxer2DTrainConfig:
    return Boxer2DTrainConfig.recipe(steps=3, batch_size=1, warmup=1, ckpt_every=1,
                                     workers=0, threads=1)


def _state(path: Path) -> dict[str, torch.Tensor]:
    return load_boxer2d(path)[0].state_dict()


def test_training_is_deterministic_and_resumes_to_the_same_weights(tmp_path: Path) -> None:
    a = train_boxer2d(_cfg(), tmp_path / "a", tmp_path / "a.pt", model_config=tiny_config())
    assert a is not None
    assert train_boxer2d(_cfg(), tmp_path / "b", tmp_path / "b.pt", model_config=tiny_config(),
                         stop_after=2) is None
    b = train_boxer2d(_cfg(), tmp_path / "b", tmp_path / "b.pt", model_config=tiny_config())
    sa, sb = _state(a), _state(b)  # type: ignore[arg-type]
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    rows = (tmp_path / "b" / "log.csv").read_text().splitlines()
    assert [r.split(",")[0] for r in rows] == ["step", "1", "2", "3"]
    with pytest.raises(ValueError, match="another run"):
        train_boxer2d(Boxer2DTrainConfig.recipe(steps=3, batch_size=1, warmup=1, lr=1e-2,
                                                workers=0, threads=1),
                      tmp_path / "b", None, model_config=tiny_config())


def test_coco_dump_has_the_calibration_fields(tmp_path: Path) -> None:
    torch.manual_seed(0)
    model = build_boxer2d(pretrained=False)
    files = dump_coco(model, "val", 1, tmp_path, max_dets=5)
    gt = json.loads(files.instances.read_text())
    res = json.loads(files.results.read_text())
    assert {img["id"] for img in gt["images"]} == {r["image_id"] for r in res}
    assert len(res) == 6 * 5
    r = res[0]
    assert {"image_id", "category_id", "bbox", "score", "logits", "layer_logits",
            "layer_boxes"} <= set(r)
    n_layers = model.config.n_decoder
    assert len(r["logits"]) == len(CLASSES) and len(r["layer_logits"]) == n_layers
    assert r["layer_boxes"][-1] == r["bbox"] and len(r["layer_boxes"]) == n_layers
    assert r["score"] == pytest.approx(1 / (1 + 2.718281828 ** -r["logits"][
        r["category_id"] - 1]), abs=1e-3)
    table = coco_ap(files.instances, files.results)
    assert set(table) == {*CLASSES, "all"} and 0.0 <= table["all"]["AP50"] <= 1.0


def test_generalized_iou_of_known_boxes() -> None:
    a = torch.tensor([[0.0, 0.0, 2.0, 2.0]])
    b = torch.tensor([[1.0, 1.0, 3.0, 3.0], [0.0, 0.0, 2.0, 2.0]])
    giou = generalized_iou(a, b)[0]
    assert giou[0] == pytest.approx(1 / 7 - (9 - 7) / 9)
    assert giou[1] == pytest.approx(1.0)


@pytest.mark.skipif(not WEIGHTS_FILE.exists(), reason="boxer2d.pt not trained yet")
def test_shipped_weights_load_and_detect() -> None:
    assert WEIGHTS_FILE.stat().st_size <= 3 * 1024 * 1024
    model, meta = load_boxer2d()
    assert not model.training and meta["steps"] == meta["train_config"]["steps"]
    frame = make_image_frame(200_000)
    with torch.no_grad():
        out = model(frame_inputs(frame.images, model.config))
    assert out["pred_logits"].shape[:3] == (model.config.n_decoder, 6,
                                            model.config.n_queries)
    assert torch.isfinite(out["pred_logits"]).all() and torch.isfinite(out["pred_boxes"]).all()
