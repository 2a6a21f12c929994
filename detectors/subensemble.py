"""Deep sub-ensembles (thesis 4.3.3): new decoder heads on the frozen trunk of a trained model.

The *trunk* is everything up to the decoder: pillar encoder, BEV backbone, heatmap query
proposal and the positional encoding (`TRUNK_MODULES`). A sub-ensemble member keeps the
trunk's weights of the base model, frozen (batch-norm statistics included), and trains a
freshly initialised *head*: the decoder layers and their class/box heads (`HEAD_MODULES`).
Members share their query proposals, so their outputs correspond query by query and merge
by query index like MC dropout, and one trunk pass serves them all (`Detector.encode` once,
`Detector.decode` per member).
"""

from __future__ import annotations

from pathlib import Path

import torch
from torch import nn

from detectors.model.detector import Detector

TRUNK_MODULES: tuple[str, ...] = ("pillars", "backbone", "queries", "position")
HEAD_MODULES: tuple[str, ...] = ("layers", "heads")


def _is_trunk(key: str) -> bool:
    return key.split(".", 1)[0] in TRUNK_MODULES


def trunk_state(model: nn.Module) -> dict[str, torch.Tensor]:
    """The trunk's entries of `model.state_dict()`."""
    return {k: v for k, v in model.state_dict().items() if _is_trunk(k)}


def attach_trunk(model: Detector, base_weights: str | Path) -> Detector:
    """Copy the trunk of the detector in `base_weights` into `model` and freeze it; the head
    keeps `model`'s (fresh) initialisation. Returns `model`."""
    from detectors.registry import load_weights

    base, _ = load_weights(Path(base_weights))
    if base.config != model.config:
        raise ValueError(f"base_weights: {base_weights} holds another detector configuration")
    missing = model.load_state_dict(trunk_state(base), strict=False)
    if missing.unexpected_keys:
        raise ValueError(f"base_weights: unexpected keys {missing.unexpected_keys[:3]}")
    for name in TRUNK_MODULES:
        for p in getattr(model, name).parameters():
            p.requires_grad_(False)
    return model


def train_mode(model: Detector, frozen_trunk: bool) -> None:
    """`model.train()`, keeping a frozen trunk in eval mode (batch norm uses its running
    statistics and does not update them)."""
    model.train()
    if frozen_trunk:
        for name in TRUNK_MODULES:
            getattr(model, name).eval()


def same_trunk(a: nn.Module, b: nn.Module) -> bool:
    """Whether two detectors have bit-identical trunks (sub-ensemble members must)."""
    sa, sb = trunk_state(a), trunk_state(b)
    return sa.keys() == sb.keys() and all(torch.equal(sa[k], sb[k]) for k in sa)
