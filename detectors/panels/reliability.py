"""Reliability diagram: accuracy (TP fraction) against confidence, per confidence bin."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

from detectors.panels import Curve


def reliability_panel(ax: Any, curves: Sequence[Curve], title: str,
                      square: bool = False) -> None:
    """Draw on `ax` the diagonal (perfect calibration), then each curve (`x` the bins' mean
    confidence, `y` their accuracy, non-finite bins left out) with round markers; both axes
    span [0, 1]; `square` makes the panel's aspect 1:1."""
    ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--")
    for curve in curves:
        conf, acc = np.asarray(curve.x, dtype=float), np.asarray(curve.y, dtype=float)
        ok = np.isfinite(conf) & np.isfinite(acc)
        ax.plot(conf[ok], acc[ok], marker="o", ms=3, **curve.style)
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.set_title(title, fontsize=9)
    if square:
        ax.set_aspect("equal")
