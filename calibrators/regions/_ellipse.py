"""Confidence ellipses of 2-D Gaussian position uncertainty (the `x, y` block of `Σ'`).

For `Σ = [[a, b], [b, c]]` with eigenvalues `λ_max >= λ_min`, the region holding a fraction
`p` of the Gaussian's mass is the ellipse with semi-axes `sqrt(λ · χ²₂(p))`, where
`χ²₂(p) = -2 log(1 - p)` is the chi-square (2 degrees of freedom) quantile, and the major
axis at angle `θ = atan2(2b, a - c) / 2` from +x, in (-pi/2, pi/2] (0 for an isotropic `Σ`).
The closed forms are exact for 2x2 matrices and vectorise over any batch.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from calibrators.core.checks import as_float_array, check_covariances
from calibrators.core.defaults import ELLIPSE_CONFIDENCE

_HUGE = 1e300   # the Mahalanobis distance under a singular Σ': outside every region


class Ellipse(NamedTuple):
    """Semi-axes and major-axis angle; arrays `[N]` for a batch, floats for one matrix.

    semi_major, semi_minor : lengths in the covariance's units (metres for x, y).
    angle : radians of the major axis from +x, counter-clockwise, in (-pi/2, pi/2].
    """

    semi_major: np.ndarray | float
    semi_minor: np.ndarray | float
    angle: np.ndarray | float


def chi2_2_quantile(confidence: float) -> float:
    """`χ²₂(p)`, the chi-square quantile with 2 degrees of freedom, `-2 log(1 - p)`."""
    p = float(confidence)
    if not 0.0 < p < 1.0:
        raise ValueError(f"confidence must be in (0, 1), got {confidence!r}")
    return float(-2.0 * np.log1p(-p))


def ellipse(cov: np.ndarray, confidence: float = ELLIPSE_CONFIDENCE) -> Ellipse:
    """Confidence ellipse of `cov [N, 2, 2]` (arrays `[N]`) or `cov [2, 2]` (floats)."""
    q = chi2_2_quantile(confidence)
    single, (high, low, angle) = _eigen(cov)
    major, minor = np.sqrt(q * high), np.sqrt(q * low)
    if single:
        return Ellipse(float(major[0]), float(minor[0]), float(angle[0]))
    return Ellipse(major, minor, angle)


def radius_ellipse(cov: np.ndarray, radius: np.ndarray) -> Ellipse:
    """Ellipses of `cov [N, 2, 2]` with Mahalanobis radius `radius [N]` (>= 0): semi-axes
    `r·sqrt(λ)`, the region `{x: xᵀ Σ⁻¹ x <= r²}` (a conformal radius, or `sqrt(χ²₂(p))`
    for the Gaussian ellipse of confidence p). An infinite radius (a conformal level beyond
    what the group's calibration points certify) is the whole plane: both semi-axes inf."""
    r = np.asarray(radius, dtype=np.float64)
    if r.ndim != 1:
        raise ValueError(f"radius must have 1 dimension, got shape {r.shape}")
    return radius_ellipses(cov, r[:, None])[0]


def radius_ellipses(cov: np.ndarray, radii: np.ndarray, *, check: bool = True
                    ) -> list[Ellipse]:
    """`radius_ellipse` of `cov [N, 2, 2]` at each column of `radii [N, Q]`: Q ellipses from
    one eigen-decomposition. `check=False` skips the symmetry / PSD test of `cov` for
    matrices built from checked ones (the serving path's `Σ + k·d·I`)."""
    r = np.asarray(radii, dtype=np.float64)
    if r.ndim != 2:
        raise ValueError(f"radii must have 2 dimensions [N, Q], got shape {r.shape}")
    if not (r >= 0).all():   # NaN fails too
        raise ValueError(f"radius must be >= 0 (inf: unbounded), got {float(r[~(r >= 0)][0])}")
    single, (high, low, angle) = _eigen(cov, check)
    if single or r.shape[0] != high.shape[0]:
        raise ValueError(f"radius must have one entry per covariance [N, 2, 2], got "
                         f"{r.shape[0]} for {high.shape[0]}")
    r = r.T                                  # [Q, N]: each level's axes contiguous
    unbounded = np.isinf(r)
    finite = np.where(unbounded, 0.0, r)
    major = np.where(unbounded, np.inf, finite * np.sqrt(high))
    minor = np.where(unbounded, np.inf, finite * np.sqrt(low))
    return [Ellipse(major[j], minor[j], angle) for j in range(r.shape[0])]


def _eigen(cov: np.ndarray, check: bool = True
           ) -> tuple[bool, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(single matrix?, (λ_max [N], λ_min [N], major-axis angle [N])) of `cov`."""
    arr = as_float_array("cov", cov) if check else np.asarray(cov, dtype=np.float64)
    single = arr.ndim == 2
    batch = arr[None] if single else arr
    if check:
        check_covariances("cov", batch, dim=2)
    a, b, c = batch[:, 0, 0], batch[:, 0, 1], batch[:, 1, 1]
    mean = 0.5 * (a + c)
    radius = np.hypot(0.5 * (a - c), b)
    # + 0.0 turns b = -0.0 into +0.0 so that a diagonal Σ with a < c gives +pi/2, not -pi/2.
    angle = 0.5 * np.arctan2(2.0 * b + 0.0, a - c)
    angle = np.where(angle <= -0.5 * np.pi, angle + np.pi, angle)  # same axis, in range
    return single, (np.maximum(mean + radius, 0.0), np.maximum(mean - radius, 0.0), angle)


def xy_mahalanobis(residuals: np.ndarray, covariances: np.ndarray, dims: tuple[str, ...]
                   ) -> np.ndarray:
    """`[M]` Mahalanobis distance of the x, y residuals under the x, y block of `Σ' [M, D, D]`
    (a singular block gives a huge distance: outside every region)."""
    ix, iy = dims.index("x"), dims.index("y")
    r = residuals[:, [ix, iy]]
    a, b, c = covariances[:, ix, ix], covariances[:, ix, iy], covariances[:, iy, iy]
    det = a * c - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        q = (c * r[:, 0] ** 2 - 2.0 * b * r[:, 0] * r[:, 1] + a * r[:, 1] ** 2) / det
    q = np.where(det > 0, q, np.inf)
    return np.minimum(np.sqrt(np.maximum(q, 0.0)), _HUGE)
