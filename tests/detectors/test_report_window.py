"""`detcal report-v2 --probe-windows`: the group model's own weights with wider attention
windows at inference, each with its mAP and final-layer trend; a model without windowed
attention is refused."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from detectors.model import Detector
from detectors.registry import load_weights, save_weights
from detectors.report.window_probe import probe_table, probe_windows
from detectors.sim import split_seeds


def test_wider_windows_run_the_same_weights(tmp_path: Path, tiny_config) -> None:
    torch.manual_seed(0)
    model = Detector(tiny_config(head="group", token_stride=1, attn_window=4)).eval()
    path = save_weights(model, tmp_path / "w4.pt", {"steps": 3})
    seeds = split_seeds("test", 2)
    probes = probe_windows(path, [8, 16], seeds, tmp_path / "cache", max_detections=20)
    assert [p.window for p in probes] == [8, 16]
    assert [p.metres for p in probes] == [8 * 1.6, 16 * 1.6]   # tiny grid: 64 cells of 1.6 m
    for p in probes:
        wide, _ = load_weights(tmp_path / "cache" / f"window{p.window}" / "weights.pt")
        assert wide.config.attn_window == p.window
        for (name, a), b in zip(model.state_dict().items(), wide.state_dict().values(),
                                strict=True):
            assert torch.equal(a, b), name
        assert 0.0 <= p.mean_ap <= 1.0 and p.trend.layer == model.config.n_layers
    table = probe_table(4, 0.1, probes[0].trend, probes, 1.6)
    assert "| 4 x 4 (6.4 m) (trained) | 0.100 |" in table
    assert "| 16 x 16 (25.6 m) |" in table


def test_a_dense_model_is_refused(tmp_path: Path, tiny_config) -> None:
    path = save_weights(Detector(tiny_config(head="group")).eval(), tmp_path / "d.pt", {})
    with pytest.raises(ValueError, match="windowed attention"):
        probe_windows(path, [8], split_seeds("test", 1), tmp_path / "cache")
