"""Average calibration plot: the observed against the expected proportion of residuals
inside the centred Gaussian interval of each level (thesis Fig. 5-8)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from detectors.panels import Curve


def calibration_curve_panel(ax: Any, curves: Sequence[Curve], title: str,
                            ylabel: str = "observed proportion in interval",
                            diagonal_label: str | None = None, square: bool = False) -> None:
    """Draw on `ax` the diagonal (perfect calibration, legend entry `diagonal_label`), then
    each curve (`x` expected, `y` observed proportion), or "no covariance" when there is
    none; `square` makes the panel's aspect 1:1."""
    ax.plot([0, 1], [0, 1], color="0.6", lw=0.8, ls="--", label=diagonal_label)
    for curve in curves:
        ax.plot(curve.x, curve.y, **curve.style)
    if not curves:
        ax.text(0.5, 0.5, "no covariance", ha="center", va="center")
    ax.set_title(title)
    ax.set_xlabel("expected proportion in interval")
    ax.set_ylabel(ylabel)
    if square:
        ax.set_aspect("equal")
