"""`detcal train --model KEY=VALUE`: an architecture tried without editing the registry."""

from __future__ import annotations

import pytest

from detectors.registry import config_with, detector_config


def test_overrides_change_only_the_named_fields() -> None:
    base = detector_config("lidar")
    cfg = config_with("lidar", ["d_model=96", "head=unified", "dropout=0.2"])
    assert (cfg.d_model, cfg.head, cfg.dropout) == (96, "unified", 0.2)
    assert cfg.token_stride == base.token_stride and cfg.classes == base.classes
    assert config_with("lidar", []) == base


@pytest.mark.parametrize(("text", "fragment"), [
    ("d_model", "KEY=VALUE"), ("nope=1", "KEY=VALUE"), ("classes=car", "KEY=VALUE"),
    ("sensor=radar1", "KEY=VALUE"), ("d_model=wide", "must be int")])
def test_bad_overrides_are_named(text: str, fragment: str) -> None:
    with pytest.raises(ValueError, match=fragment):
        config_with("lidar", [text])


def test_the_cli_passes_them_to_training() -> None:
    import argparse

    from detectors.cli import register

    parser = argparse.ArgumentParser()
    register(parser.add_subparsers())
    args = parser.parse_args(["train", "--sensor", "lidar", "--model", "d_model=96",
                              "--model", "n_heads=8"])
    assert args.model == ["d_model=96", "n_heads=8"]
    assert config_with(args.sensor, args.model).n_heads == 8
