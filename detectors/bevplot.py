"""Matplotlib pieces shared by every bird's-eye view (`detcal show`, the report's BEV plot)."""

from __future__ import annotations

import math
from typing import Any

from calibrators.ellipse import Ellipse


def add_ellipse(ax: Any, x: float, y: float, ell: Ellipse, j: int, color: str) -> None:
    """Draw ellipse `j` of `ell` centred at (x, y) metres."""
    from matplotlib.patches import Ellipse as EllipsePatch

    ax.add_patch(EllipsePatch((x, y), 2 * ell.semi_major[j], 2 * ell.semi_minor[j],
                              angle=math.degrees(ell.angle[j]), fill=False, color=color,
                              lw=0.9))


def finish_bev_axes(ax: Any, half: float) -> None:
    """The ego marker, a square [-half, half]^2 view in metres and the axis labels."""
    ax.plot([0], [0], marker="^", color="black", ms=8)
    ax.set_xlim(-half, half)
    ax.set_ylim(-half, half)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
