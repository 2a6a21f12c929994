"""Average calibration curve and miscalibration area of 1-D Gaussian predictions.

These follow uncertainty-toolbox (`metrics_calibration.get_proportion_lists_vectorized`
with `prop_type="interval"` and `miscalibration_area`):
- expected proportions p_m = linspace(0, 1, n_bins);
- observed proportion = fraction of standardised residuals z_i = r_i / σ_i with
  Φ⁻¹(0.5 − p_m/2) <= z_i <= Φ⁻¹(0.5 + p_m/2) (the central p_m interval; p = 1 gives ±inf);
- miscalibration area = area between the piecewise-linear curve (p_m, obs_m) and the diagonal.

Differences from uncertainty-toolbox, none of which change the numbers beyond float rounding:
it takes `y_pred, y_std, y_true` and uses `y_pred − y_true`; we take the residual directly
(the interval is symmetric, so the sign only matters for a z exactly on a bound, up to one ulp
of Φ⁻¹). It counts with an [N, M] boolean matrix; we sort z once and use binary search
(O(N log N), no N × M memory). It measures the area with shapely (polygonize the self-
intersecting ring curve → diagonal); we integrate |obs − p| exactly on each segment of the
linear interpolation, splitting a segment where it crosses the diagonal — the same area.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from calibrators.core.bins import ResultMixin, check_n_bins, check_nonempty
from calibrators.core.checks import as_float_array, check_length


@dataclass(frozen=True)
class CalibrationCurve(ResultMixin):
    """Average calibration curve: expected [M] vs observed [M] interval proportions."""

    expected: np.ndarray
    observed: np.ndarray


def average_calibration_curve(residuals_1d: np.ndarray, std_1d: np.ndarray,
                              n_bins: int = 100) -> CalibrationCurve:
    """Observed vs expected proportion inside central Gaussian intervals.

    residuals_1d: [N] y_gt − y_pred; std_1d: [N] predicted standard deviation (> 0);
    n_bins: number of expected proportions M (>= 2), evenly spaced on [0, 1].
    """
    n_bins = check_n_bins("n_bins", n_bins, minimum=2)
    r = as_float_array("residuals_1d", residuals_1d, ndim=1)
    check_nonempty("residuals_1d", r)
    std = as_float_array("std_1d", std_1d, ndim=1)
    check_length("std_1d", std, r.shape[0], "residuals_1d")
    if (std <= 0).any():
        i = int(np.argmax(std <= 0))
        raise ValueError(f"std_1d must be > 0; entry {i} is {std[i]}")
    expected = np.linspace(0.0, 1.0, n_bins)
    lower = stats.norm.ppf(0.5 - expected / 2.0)
    upper = stats.norm.ppf(0.5 + expected / 2.0)
    z = np.sort(r / std)
    inside = np.searchsorted(z, upper, side="right") - np.searchsorted(z, lower, side="left")
    return CalibrationCurve(expected, inside / z.shape[0])


def _area_between(x: np.ndarray, y: np.ndarray) -> float:
    """Exact ∫|y(t) − t| dt of the piecewise-linear y through (x_m, y_m)."""
    d = y - x
    h = np.diff(x)
    d0, d1 = d[:-1], d[1:]
    a0, a1 = np.abs(d0), np.abs(d1)
    crossing = d0 * d1 < 0
    denom = np.where(crossing, a0 + a1, 1.0)
    area = np.where(crossing, (d0**2 + d1**2) / denom, a0 + a1) * h / 2.0
    return float(np.sum(area))


def miscalibration_area(residuals_1d: np.ndarray, std_1d: np.ndarray,
                        n_bins: int = 100) -> float:
    """Area between the average calibration curve and the diagonal (0 = calibrated, max 0.5).

    residuals_1d: [N]; std_1d: [N] > 0; n_bins: M >= 2 (see `average_calibration_curve`).
    """
    curve = average_calibration_curve(residuals_1d, std_1d, n_bins)
    return _area_between(curve.expected, curve.observed)
