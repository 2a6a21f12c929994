"""`build_detector(name)`: the only place that knows each sensor's detector configuration.

Shipped weights live in `detectors/weights/{name}.pt`: a torch file holding
`{"format": "detcal-detector-v1", "config": <DetectorConfig JSON>, "state_dict": ...,
"meta": {...}}` (state dict in float32, each file <= 10 MB). They are loaded on the CPU,
with `weights_only=True`, and the model is returned in eval mode. No download ever happens.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import fields, replace
from pathlib import Path
from typing import Any

import torch

from detectors.model.detector import Detector, DetectorConfig
from detectors.vocab import SENSORS

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
WEIGHTS_FORMAT = "detcal-detector-v1"
MAX_WEIGHTS_BYTES = 10 * 1024 * 1024

# Per-sensor hyper-parameters on top of DetectorConfig's defaults (the lidar recipe).
# Radar and camera clouds are sparse or smeared in range, so their backbones see the same
# grid; only the point features differ (taken from detectors.sim.FEATURES).
_SENSOR_OVERRIDES: dict[str, dict[str, Any]] = {name: {} for name in SENSORS}
# Lidar v2 (issue 13): group regression heads (seed 001) and cross-attention over seed 000's
# 128 x 128 grid of 0.8 m tokens, each query attending to the 8 x 8 tokens (6.4 m) around
# its anchor (dense attention over all 16 384 tokens costs ~140 ms/frame, over the 50 ms
# budget; see docs/detectors.md). Weights files carry their own configuration, so the v1
# lidar detector (unified head, 3.2 m tokens; lidar_de0.pt, the report's deep-ensemble
# member 0) still loads.
_SENSOR_OVERRIDES["lidar"] = {"head": "group", "token_stride": 1, "attn_window": 8}

# Training recipe per sensor (detectors.train reads it; `detcal train --steps` overrides).
# 4000 steps x 4 frames: ~26 min for lidar on the shared 2-core machine.
_RECIPE: dict[str, Any] = {"steps": 4000, "batch_size": 4, "lr": 2e-3, "weight_decay": 1e-2,
                           "seed": 0}
TRAIN_RECIPES: dict[str, dict[str, Any]] = {name: dict(_RECIPE) for name in _SENSOR_OVERRIDES}
# Lidar adds rare-class over-sampling (mean extra objects per training scene; see
# detectors.sim.traffic.place_extra): about 4x the buses, trailers, construction vehicles,
# motorcycles and bicycles the world's own frequencies give.
TRAIN_RECIPES["lidar"]["extra_objects"] = {
    "truck": 1.0, "bus": 2.0, "trailer": 2.0, "construction_vehicle": 2.0,
    "motorcycle": 2.0, "bicycle": 2.0}
# Lidar v2: 8000 steps, the last 1/8 without object sampling (seed 001's fade-out: 5 of its
# 40 epochs), every simulated scene shown twice (16 000 scenes): the simulation costs 0.2 s
# of a 0.5 s step, so a step costs ~0.41 s on the 2 cores on average (~55 min).
TRAIN_RECIPES["lidar"].update({"steps": 8000, "extra_fade": 0.125, "scene_reuse": 2})
# A deep sub-ensemble head (`detcal train --base-weights`): the trunk is trained already, so
# a fresh decoder head needs fewer steps; everything else is the sensor's recipe.
SUB_ENSEMBLE_RECIPE: dict[str, Any] = {"steps": 1500, "warmup": 100}


def sensor_names() -> tuple[str, ...]:
    """The sensors that have a detector configuration: every one of `detectors.vocab.SENSORS`."""
    return SENSORS


def _check_name(name: str) -> None:
    if name not in SENSORS:
        raise ValueError(f"name must be one of {list(SENSORS)}, got {name!r}")


def detector_config(name: str) -> DetectorConfig:
    """The configuration of sensor `name`'s detector (features and classes from the sim)."""
    _check_name(name)
    from detectors.sim import CLASSES, FEATURES

    return DetectorConfig(sensor=name, features=tuple(FEATURES[name]), classes=tuple(CLASSES),
                          **_SENSOR_OVERRIDES[name])


def config_with(name: str, overrides: Sequence[str]) -> DetectorConfig:
    """`detector_config(name)` with `KEY=VALUE` overrides of its scalar fields (int, float,
    str: `d_model=96`, `token_stride=4`, `head=unified`), for trying an architecture without
    editing the registry; a ValueError names a key that is not a scalar field or a value of
    the wrong type."""
    base = detector_config(name)
    kinds = {f.name: type(getattr(base, f.name)) for f in fields(base)}
    changes: dict[str, Any] = {}
    for text in overrides:
        key, sep, value = text.partition("=")
        kind = kinds.get(key)
        if not sep or kind not in (int, float, str) or key in ("sensor",):
            scalars = sorted(k for k, t in kinds.items() if t in (int, float, str)
                             and k != "sensor")
            raise ValueError(f"--model takes KEY=VALUE with KEY one of {scalars}, got {text!r}")
        try:
            changes[key] = kind(value)
        except ValueError:
            raise ValueError(f"--model {key} must be {kind.__name__}, got {value!r}") from None
    return replace(base, **changes)


def weights_path(name: str) -> Path:
    """Where the shipped weights of sensor `name` live."""
    _check_name(name)
    return WEIGHTS_DIR / f"{name}.pt"


def save_weights(model: Detector, path: str | Path, meta: dict[str, Any] | None = None) -> Path:
    """Write `model`'s config and float32 state dict to `path`; refuses files over 10 MB."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    payload = {"format": WEIGHTS_FORMAT, "config": json.dumps(model.config.to_dict()),
               "state_dict": state, "meta": json.dumps(meta or {})}
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    size = tmp.stat().st_size
    if size > MAX_WEIGHTS_BYTES:
        tmp.unlink()
        raise ValueError(f"weights for {path.name} would be {size} bytes, over the "
                         f"{MAX_WEIGHTS_BYTES}-byte limit")
    tmp.replace(path)
    return path


def load_weights(path: str | Path) -> tuple[Detector, dict[str, Any]]:
    """Load a weights file written by `save_weights` -> (model in eval mode on CPU, meta)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"detector weights not found: {path}")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != WEIGHTS_FORMAT:
        raise ValueError(f"{path} is not a {WEIGHTS_FORMAT} weights file")
    config = DetectorConfig.from_dict(json.loads(payload["config"]))
    model = Detector(config)
    model.load_state_dict(payload["state_dict"])
    return model.eval(), json.loads(payload.get("meta", "{}"))


def build_detector(name: str, pretrained: bool = True,
                   weights: str | Path | None = None) -> Detector:
    """The detector of sensor `name` (one of `detectors.vocab.SENSORS`).

    With `pretrained` (default) the shipped weights (or the file `weights`) are loaded on the
    CPU and the model is returned in eval mode; a missing file raises FileNotFoundError
    naming it and the command that trains it. Without, a freshly initialised model in train
    mode is returned (what `detcal train` starts from).
    """
    _check_name(name)
    if not pretrained:
        return Detector(detector_config(name))
    path = Path(weights) if weights is not None else weights_path(name)
    if not path.exists():
        raise FileNotFoundError(f"detector weights for {name!r} not found at {path}; "
                                f"train them with `detcal train --sensor {name}`")
    model, _ = load_weights(path)
    if model.config.sensor != name:
        raise ValueError(f"{path} holds a {model.config.sensor!r} detector, not {name!r}")
    return model
