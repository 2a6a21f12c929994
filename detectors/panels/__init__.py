"""Matplotlib panels shared by every picture detcal draws: the report's figures
(`detectors.report.plots`), `detcal show` (`detectors.show`) and the dashboard
(`app.dashboard.plots`).

One module per kind of panel, each drawing on an `Axes` it is given (the caller owns the
figure, its size, its text and how it is saved):

- `reliability`: accuracy against confidence per bin (reliability diagram);
- `calibration_curve`: observed against expected proportion in interval (average
  calibration plot);
- `bev`: a bird's-eye view of one frame: points, ground truth, detections, ellipses, ego.

Here: `pyplot()` and `panel_grid()`. Importing this package or any of its modules loads
neither matplotlib, torch nor the simulator; `pyplot()` imports matplotlib (Agg backend)
when something is drawn.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, NamedTuple

import numpy as np


class Curve(NamedTuple):
    """One line of a panel: `x [K]`, `y [K]` and its `Axes.plot` keywords (colour, label)."""

    x: np.ndarray
    y: np.ndarray
    style: Mapping[str, Any]


def pyplot() -> Any:
    """`matplotlib.pyplot` with the Agg backend (files and strings, never a window)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def panel_grid(n: int, cols: int, width: float, height: float) -> tuple[Any, np.ndarray]:
    """A figure for `n` panels in rows of `cols`, each `width` x `height` inches ->
    (figure, axes `[rows, cols]`); panel `i` is `axes.flat[i]`, the spare cells are hidden."""
    rows = max(1, math.ceil(n / cols))
    fig, axes = pyplot().subplots(rows, cols, figsize=(width * cols, height * rows),
                                  squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    return fig, axes
