"""Deep sub-ensembles: a new head on the frozen trunk of a trained model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from detectors.model import Detector
from detectors.registry import load_weights, save_weights
from detectors.subensemble import HEAD_MODULES, attach_trunk, same_trunk, trunk_state
from detectors.train import TrainConfig, train


def _cfg(**overrides: object) -> TrainConfig:
    return TrainConfig.for_sensor("lidar", steps=3, batch_size=2, warmup=1, ckpt_every=3,
                                  workers=0, threads=1, **overrides)


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """(tiny base weights, a sub-ensemble head on its trunk, an unrelated tiny model)."""
    from tests.detectors.conftest import _tiny

    root = tmp_path_factory.mktemp("dse")
    model_cfg = _tiny()
    base = train(_cfg(), run_dir=root / "base", weights_out=root / "base.pt",
                 progress=False, model_config=model_cfg)
    head = train(_cfg(seed=1, base_weights=str(base.weights)), run_dir=root / "dse",
                 weights_out=root / "dse.pt", progress=False, model_config=model_cfg)
    torch.manual_seed(5)
    other = save_weights(Detector(model_cfg).eval(), root / "other.pt")
    return base.weights, head.weights, other


def test_head_trains_on_a_frozen_trunk(trained: tuple[Path, Path, Path]) -> None:
    a, _ = load_weights(trained[0])
    b, meta = load_weights(trained[1])
    # trunk bit-identical, batch-norm running statistics included (they must not update)
    assert same_trunk(a, b)
    assert any("running_mean" in k for k in trunk_state(a))
    # the head is a different, trained one
    sa, sb = a.state_dict(), b.state_dict()
    head_keys = [k for k in sa if k.split(".", 1)[0] in HEAD_MODULES]
    assert head_keys and all(not torch.equal(sa[k], sb[k]) for k in head_keys
                             if sa[k].dtype.is_floating_point and sa[k].numel() > 1)
    assert "--base-weights" in meta["command"]


def test_encode_then_decode_is_forward(tiny_config) -> None:
    torch.manual_seed(0)
    model = Detector(tiny_config()).eval()
    points = [torch.randn(300, len(model.config.features)) * 10]
    with torch.no_grad():
        full = model(points)
        split = model.decode(model.encode(points))
    for key in ("pred_logits", "pred_boxes", "attention"):
        assert torch.equal(full[key], split[key]), key


def test_attach_trunk_refuses_another_configuration(tmp_path: Path, tiny_config) -> None:
    other = Detector(tiny_config(d_model=16, n_heads=2))
    path = save_weights(other.eval(), tmp_path / "other.pt")
    with pytest.raises(ValueError, match="base_weights"):
        attach_trunk(Detector(tiny_config()), path)


def test_report_runs_the_trunk_once_and_every_head(trained: tuple[Path, Path, Path],
                                                   tmp_path: Path) -> None:
    from detectors.report.runner import MethodSpec, run_split
    from detectors.sim import split_seeds

    base, head, other = trained
    seeds = split_seeds("test", 2)
    _, passes = run_split("lidar", seeds, [MethodSpec("dse", (base, head), 2)], tmp_path,
                          "test", max_detections=10)
    dse = passes["dse"]
    assert dse.n_members == 2 and dse.seconds.shape == (2,)
    q = load_weights(base)[0].config.n_queries
    assert len(dse.member) == 2 * 2 * q          # every query of both heads on both frames
    # member 0 is exactly the base model's final layer
    from detectors.sim import make_frame

    model = load_weights(base)[0]
    with torch.no_grad():
        out = model([torch.from_numpy(make_frame(seeds[0], "lidar").points.copy())])
    rows = (dse.member == 0) & (dse.frame == 0)
    np.testing.assert_allclose(dse.layer_logits[rows, 0], out["pred_logits"][-1, 0].numpy(),
                               rtol=1e-5, atol=1e-5)
    assert not np.allclose(dse.layer_logits[(dse.member == 1) & (dse.frame == 0), 0],
                           dse.layer_logits[rows, 0])
    with pytest.raises(ValueError, match="trunk differs"):
        run_split("lidar", seeds, [MethodSpec("dse", (base, other), 2)], tmp_path / "x",
                  "test", max_detections=10)


def test_resume_refuses_another_base_model(tmp_path: Path, tiny_config) -> None:
    model_cfg = tiny_config()
    base = train(_cfg(), run_dir=tmp_path / "base", weights_out=tmp_path / "base.pt",
                 progress=False, model_config=model_cfg)
    with pytest.raises(ValueError, match="base model"):
        train(_cfg(base_weights=str(base.weights)), run_dir=tmp_path / "base",
              weights_out=tmp_path / "x.pt", progress=False, model_config=model_cfg)


def test_report_refuses_heads_of_another_trunk(trained: tuple[Path, Path, Path], tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    import shutil

    import detectors.registry as registry
    from detectors.report.sensor import _check_sub_ensemble

    base, head, other = trained
    monkeypatch.setattr(registry, "WEIGHTS_DIR", tmp_path)
    shutil.copy(base, tmp_path / "lidar.pt")
    _check_sub_ensemble("lidar", (head,))             # a head on the shipped trunk: fine
    with pytest.raises(ValueError, match="not trained on the trunk of lidar.pt"):
        _check_sub_ensemble("lidar", (head, other))
    # A DE member 0 of its own (the shipped model moved on): the heads must sit on it.
    shutil.copy(base, tmp_path / "lidar_de0.pt")
    shutil.copy(other, tmp_path / "lidar.pt")
    _check_sub_ensemble("lidar", (head,))
    with pytest.raises(ValueError, match="trunk of lidar_de0.pt"):
        _check_sub_ensemble("lidar", (other,))
