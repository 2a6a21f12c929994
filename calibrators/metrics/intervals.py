"""Sampling intervals of measured proportions (coverage, accuracy) and the allowance a served
level gets for test sampling.

- `proportion_bounds(hits, n)`: Clopper-Pearson (exact binomial) bounds of `hits / n`;
- `coverage_allowance(q, n)`: the lowest coverage of `n` test points that is still consistent
  with a served level `q`: `q − 0.02 − 2.33·sqrt(q(1 − q)/n)`, a one-sided 99 % test-sampling
  allowance plus 2 pp for calibration sampling (the per-cell criterion of docs/science.md).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

#: Confidence of the intervals the service prints.
INTERVAL_CONFIDENCE = 0.95


def proportion_bounds(hits: np.ndarray | float, n: np.ndarray | int,
                      confidence: float = INTERVAL_CONFIDENCE) -> tuple[np.ndarray, np.ndarray]:
    """Clopper-Pearson bounds `(lo, hi)` of `hits / n`, elementwise over arrays of the same
    shape (NaN where n = 0)."""
    k = np.asarray(hits, dtype=np.float64)
    m = np.asarray(n, dtype=np.float64)
    a = (1.0 - confidence) / 2.0
    with np.errstate(invalid="ignore", divide="ignore"):
        lo = np.where(k > 0, stats.beta.ppf(a, k, m - k + 1), 0.0)
        hi = np.where(k < m, stats.beta.ppf(1 - a, k + 1, m - k), 1.0)
    empty = m <= 0
    return np.where(empty, np.nan, lo), np.where(empty, np.nan, hi)


def coverage_allowance(level: float | np.ndarray, n: int | np.ndarray) -> np.ndarray:
    """`q − 0.02 − 2.33·sqrt(q(1 − q)/n)` for served `level` q and `n` test points (module
    docstring); elementwise."""
    q = np.asarray(level, dtype=np.float64)
    return q - 0.02 - 2.33 * np.sqrt(q * (1.0 - q) / np.asarray(n, dtype=np.float64))
