"""Shared fixtures of the detector tests (owner: detectors model/training)."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from detectors.model import DetectorConfig
from detectors.sim import CLASSES, FEATURES


def _tiny(sensor: str = "lidar", **overrides: object) -> DetectorConfig:
    base = dict(sensor=sensor, features=tuple(FEATURES[sensor]), classes=CLASSES,
                grid_size=64, grid_cell=1.6, pillar_channels=16, c1=24, c2=32, d_model=32,
                n_heads=2, d_ffn=64, n_layers=2, n_queries=40, dropout=0.0)
    base.update(overrides)
    return DetectorConfig(**base)  # type: ignore[arg-type]


@pytest.fixture
def tiny_config() -> Callable[..., DetectorConfig]:
    """Factory of a tiny detector configuration (64 x 64 grid of 1.6 m, d_model 32)."""
    return _tiny
