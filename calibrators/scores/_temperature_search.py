"""Bounded Brent's minimisation of a temperature-scaling NLL on `log T` (small sigmoid fits
and `TemperatureScaler.fit_objective`), widening a bracket whose optimum sits at an inner
edge instead of falling back to the full bounds."""

from __future__ import annotations

from scipy.optimize import minimize_scalar

from calibrators.scores._temperature_nll import Objective


def search_log_t(objective: Objective, bracket: tuple[float, float],
                 bounds: tuple[float, float], xtol: float) -> tuple[float, float, int]:
    """Bounded Brent on `log T` in `bracket`, then, while the optimum sits at an end of the
    bracket that is not an end of `bounds`, again on a bracket five times as wide on that
    side (the NLL is unimodal in log T, so the optimum lies beyond that end).
    Returns (argmin, minimum, number of evaluations)."""
    log_t, nll, n_evaluations = _brent(objective, bracket, xtol)
    while bracket != bounds and _at_inner_edge(log_t, bracket, bounds, xtol):
        width = bracket[1] - bracket[0]
        if log_t - bracket[0] < 10 * xtol:
            bracket = (max(bounds[0], bracket[0] - 4 * width), bracket[0] + width)
        else:
            bracket = (bracket[1] - width, min(bounds[1], bracket[1] + 4 * width))
        log_t, nll, extra = _brent(objective, bracket, xtol)
        n_evaluations += extra
    return log_t, nll, n_evaluations


def _brent(objective: Objective, bracket: tuple[float, float], xtol: float
           ) -> tuple[float, float, int]:
    """Bounded Brent on `log T` in `bracket`: (argmin, minimum, number of evaluations)."""
    result = minimize_scalar(objective, bounds=bracket, method="bounded",
                             options={"xatol": xtol})
    return float(result.x), float(result.fun), int(result.nfev)


def _at_inner_edge(x: float, bracket: tuple[float, float], bounds: tuple[float, float],
                   xtol: float) -> bool:
    """Whether `x` lies at an end of `bracket` that is not also an end of `bounds`."""
    return ((x - bracket[0] < 10 * xtol and bracket[0] > bounds[0])
            or (bracket[1] - x < 10 * xtol and bracket[1] < bounds[1]))
