"""Bounded Brent's minimisation of a depth-scaling NLL over `k` (on log k), for the exact
(`DepthTerms`) and binned (`DepthBins`) NLLs of `_depth_nll`."""

from __future__ import annotations

import warnings
from collections.abc import Hashable
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import minimize_scalar

if TYPE_CHECKING:
    from calibrators.covariance._depth_nll import DepthBins, DepthTerms

_WIDEN = 100.0  # an optimum at the upper bound is searched again once up to 100 x the bound


def fit_k(stats: DepthBins | DepthTerms, bounds: tuple[float, float], xtol: float,
           label: Hashable) -> float:
    """Minimise `stats.nll` over k in `bounds`: Brent on log k (see `brent_k`), widened once if
    the optimum is at the upper bound, then compared with k = low itself (k = 0 is valid)."""
    low, high = bounds
    k, nll = brent_k(stats, low, high, xtol)
    if _at_edge(k, high, xtol):
        k, nll = brent_k(stats, low, high * _WIDEN, xtol)
        if _at_edge(k, high * _WIDEN, xtol):
            warnings.warn(f"depth k for class {label!r} is at the search edge {high * _WIDEN}; "
                          "the residuals may not grow with distance", RuntimeWarning,
                          stacklevel=3)
    return float(low) if stats.nll(low) <= nll else float(k)


def _at_edge(k: float, high: float, xtol: float) -> bool:
    return np.log(high) - np.log(k) < 10 * xtol


def brent_k(stats: DepthBins | DepthTerms, low: float, high: float, xtol: float
           ) -> tuple[float, float]:
    """Bounded Brent on log k in [log max(low, 1e-9·high), log high]; `xtol` is on log k.

    Log k reaches the scale of k (1e-3 .. 1 m²/m) in a few steps where a linear search from
    [0, 25] spends a dozen golden-section steps; values below 1e-9·high are covered by the
    k = low check in `fit_k`.
    """
    lo = np.log(max(low, 1e-9 * high))
    result = minimize_scalar(lambda u: stats.nll(float(np.exp(u))), bounds=(lo, np.log(high)),
                             method="bounded", options={"xatol": xtol})
    return float(np.exp(result.x)), float(result.fun)
