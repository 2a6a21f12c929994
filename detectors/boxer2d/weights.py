"""Shipped weights of the image-plane detector: `detectors/weights/boxer2d.pt`.

The file has the layout of the other detectors' (`detectors.registry`): a torch file holding
`{"format": "detcal-boxer2d-v1", "config": <Boxer2DConfig JSON>, "state_dict": ...,
"meta": {...}}`, float32, within `registry.MAX_WEIGHTS_BYTES`; loaded on the CPU with
`weights_only=True`, the model returned in eval mode. No download ever happens.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from detectors.boxer2d.config import Boxer2DConfig
from detectors.boxer2d.model import Boxer2D
from detectors.registry import MAX_WEIGHTS_BYTES, WEIGHTS_DIR

WEIGHTS_FORMAT = "detcal-boxer2d-v1"
WEIGHTS_FILE = WEIGHTS_DIR / "boxer2d.pt"


def default_config() -> Boxer2DConfig:
    """The shipped architecture (classes from the simulator, `CLASSES` order)."""
    from detectors.sim import CLASSES

    return Boxer2DConfig(classes=tuple(CLASSES))


def save_boxer2d(model: Boxer2D, path: str | Path, meta: dict[str, Any] | None = None
                 ) -> Path:
    """Write `model`'s config and float32 state dict to `path`; refuses files over 10 MB."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().float().clone() for k, v in model.state_dict().items()}
    payload = {"format": WEIGHTS_FORMAT, "config": json.dumps(model.config.to_dict()),
               "state_dict": state, "meta": json.dumps(meta or {})}
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    if tmp.stat().st_size > MAX_WEIGHTS_BYTES:
        size = tmp.stat().st_size
        tmp.unlink()
        raise ValueError(f"weights for {path.name} would be {size} bytes, over the "
                         f"{MAX_WEIGHTS_BYTES}-byte limit")
    tmp.replace(path)
    return path


def load_boxer2d(path: str | Path = WEIGHTS_FILE) -> tuple[Boxer2D, dict[str, Any]]:
    """Load a file written by `save_boxer2d` -> (model in eval mode on the CPU, meta)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"boxer2d weights not found at {path}; train them with "
                                "`python -m detectors.boxer2d train`")
    payload = torch.load(path, map_location="cpu", weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != WEIGHTS_FORMAT:
        raise ValueError(f"{path} is not a {WEIGHTS_FORMAT} weights file")
    model = Boxer2D(Boxer2DConfig.from_dict(json.loads(payload["config"])))
    model.load_state_dict(payload["state_dict"])
    return model.eval(), json.loads(payload.get("meta", "{}"))


def build_boxer2d(pretrained: bool = True, weights: str | Path | None = None) -> Boxer2D:
    """The image-plane detector: the shipped weights (or the file `weights`) in eval mode,
    or, without `pretrained`, a fresh model in train mode."""
    if not pretrained:
        return Boxer2D(default_config())
    return load_boxer2d(weights if weights is not None else WEIGHTS_FILE)[0]
