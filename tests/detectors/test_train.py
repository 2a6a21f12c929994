"""Training is deterministic from its seed and resumes from a checkpoint exactly."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from detectors.registry import load_weights
from detectors.train import TrainConfig, learning_rate, train


class _Stop(Exception):
    pass


def _cfg() -> TrainConfig:
    return TrainConfig.for_sensor("lidar", steps=4, batch_size=2, warmup=2, ckpt_every=2,
                                  workers=0, threads=1)


def test_interrupted_run_resumes_to_the_same_weights(tmp_path: Path, tiny_config) -> None:
    cfg, model_cfg = _cfg(), tiny_config()
    straight = train(cfg, run_dir=tmp_path / "a", weights_out=tmp_path / "a.pt",
                     progress=False, model_config=model_cfg)
    assert straight.steps == 4 and straight.weights is not None

    def stop_after_checkpoint(step: int, _: dict[str, float]) -> None:
        if step == 3:
            raise _Stop

    with pytest.raises(_Stop):
        train(cfg, run_dir=tmp_path / "b", weights_out=tmp_path / "b.pt", progress=False,
              on_step=stop_after_checkpoint, model_config=model_cfg)
    assert not (tmp_path / "b.pt").exists()
    resumed = train(cfg, run_dir=tmp_path / "b", weights_out=tmp_path / "b.pt", progress=False,
                    model_config=model_cfg)
    assert resumed.steps == 4

    a, meta = load_weights(tmp_path / "a.pt")
    b, _ = load_weights(tmp_path / "b.pt")
    for (name, pa), pb in zip(a.state_dict().items(), b.state_dict().values(), strict=True):
        assert torch.equal(pa, pb), name
    assert meta["steps"] == 4 and set(meta["final_losses"]) >= {"loss", "cls", "box"}
    rows = (tmp_path / "b" / "log.csv").read_text().strip().splitlines()
    assert [r.split(",")[0] for r in rows[1:]] == ["1", "2", "3", "4"]


def test_learning_rate_warms_up_then_decays() -> None:
    cfg = TrainConfig.for_sensor("lidar", steps=1000, warmup=100, lr=1e-3)
    lrs = [learning_rate(cfg, s) for s in range(1000)]
    assert lrs[0] == pytest.approx(1e-5) and lrs[99] == pytest.approx(1e-3)
    assert all(x >= y for x, y in zip(lrs[100:], lrs[101:], strict=False))
    assert lrs[-1] == pytest.approx(cfg.lr * cfg.min_lr_ratio, rel=1e-2)


@pytest.mark.parametrize("field", ["steps", "batch_size", "threads"])
def test_bad_config_is_a_named_error(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        TrainConfig.for_sensor("lidar", **{field: 0})


def test_snapshots_keep_the_weights_of_every_nth_step(tmp_path: Path, tiny_config) -> None:
    cfg = TrainConfig.for_sensor("lidar", steps=4, batch_size=2, warmup=2, ckpt_every=2,
                                 workers=0, threads=1, snapshot_every=2)
    train(cfg, run_dir=tmp_path / "run", weights_out=tmp_path / "final.pt", progress=False,
          model_config=tiny_config())
    kept = sorted(p.name for p in (tmp_path / "run").glob("step_*.pt"))
    assert kept == ["step_2.pt"]                 # the last step is the weights file itself
    snap, meta = load_weights(tmp_path / "run" / "step_2.pt")
    final, _ = load_weights(tmp_path / "final.pt")
    assert meta["steps"] == 2
    assert any(not torch.equal(a, b) for a, b in zip(snap.state_dict().values(),
                                                     final.state_dict().values(), strict=True))


def test_device_and_snapshot_settings_are_checked() -> None:
    with pytest.raises(ValueError, match="device"):
        TrainConfig.for_sensor("lidar", device="gpu0")
    with pytest.raises(ValueError, match="snapshot_every"):
        TrainConfig.for_sensor("lidar", snapshot_every=-1)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_training_runs_on_a_cuda_device(tmp_path: Path, tiny_config) -> None:
    cfg = TrainConfig.for_sensor("lidar", steps=2, batch_size=2, warmup=1, workers=0,
                                 threads=1, device="cuda")
    result = train(cfg, run_dir=tmp_path / "run", weights_out=tmp_path / "w.pt",
                   progress=False, model_config=tiny_config())
    model, _ = load_weights(tmp_path / "w.pt")
    assert result.steps == 2 and next(model.parameters()).device.type == "cpu"
    assert all(torch.isfinite(v).all() for v in model.state_dict().values()
               if v.is_floating_point())
