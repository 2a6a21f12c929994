"""A weights file from a training checkpoint (for reports on a model still training).

`detcal train` writes `runs/SENSOR/ckpt.pt` every `ckpt_every` steps (model + optimiser
state, `model_config`, `step`) and the weights file only at the end; this turns a checkpoint
into a weights file `registry.load_weights` reads, e.g.

    .venv/bin/python -m detectors.report.checkpoint_weights runs/lidar_v2/ckpt.pt /tmp/v2_dev.pt
"""

from __future__ import annotations

import sys
from pathlib import Path


def checkpoint_to_weights(ckpt: str | Path, out: str | Path) -> Path:
    """Write the model of checkpoint `ckpt` as the weights file `out` (meta: source, step)."""
    import torch

    from detectors.model import Detector, DetectorConfig
    from detectors.registry import save_weights

    state = torch.load(Path(ckpt), map_location="cpu", weights_only=False)
    if "model" not in state or "model_config" not in state:
        raise ValueError(f"{ckpt} is not a `detcal train` checkpoint (no model / model_config)")
    model = Detector(DetectorConfig.from_dict(state["model_config"]))
    model.load_state_dict(state["model"])
    meta = {"from_checkpoint": str(ckpt), "steps": int(state.get("step", -1))}
    return save_weights(model.eval(), out, meta)


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit("usage: python -m detectors.report.checkpoint_weights CKPT OUT")
    print(checkpoint_to_weights(sys.argv[1], sys.argv[2]))
