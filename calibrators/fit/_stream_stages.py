"""The covariance and region stages of a streamed fit (`calibrators.fit._stream`), from what
the parts' first passes return: the calibration frames drawn as `fit_profile` draws them, the
depth and shrinkage scalers fit on summed statistics and chosen by the calibration true
positives' regression NLL, and the conformal radii of those true positives' scores."""

from __future__ import annotations

import warnings
from functools import reduce
from operator import add
from typing import Any

import numpy as np

from calibrators.core.selection import choose_lowest_nll
from calibrators.core.vocab import COV_METHODS
from calibrators.covariance import BinSums, fit_inputs, near_zero_q
from calibrators.data import held_out_frames
from calibrators.fit._chunks import CalibrationTPs, FirstPass
from calibrators.fit._options import FitOptions
from calibrators.fit._pipeline import has_calibration_part
from calibrators.fit._region_stage import (
    CovarianceFit,
    RegionFit,
    covariance_fit,
    make_scaler,
    region_fit_of_scores,
    regression_nll_or_none,
)
from calibrators.fit._stream_cross import calibration_scores

__all__ = ["calibration_frames", "refit_covariance", "stream_covariance", "stream_regions"]


def calibration_frames(frame_ids: np.ndarray, held: np.ndarray, opts: FitOptions
                        ) -> np.ndarray | None:
    """`[F]` the frames of the calibration part, drawn among the fit frames as `fit_profile`
    draws them (its `_calibration_split`), or None when the fit has none (nothing to choose
    and gaussian regions, `calibration=0`, fewer than 2 fit frames)."""
    fit = np.flatnonzero(~held)
    if not has_calibration_part(opts, fit.size):
        return None
    out = np.zeros(len(frame_ids), dtype=bool)
    out[fit] = held_out_frames(frame_ids[fit], opts.calibration, opts.seed + 1)
    return out


def stream_regions(classes: tuple[str, ...], opts: FitOptions, covs: dict[str, CovarianceFit],
                   tps: list[CalibrationTPs] | None) -> dict[str, RegionFit | None]:
    """The region stage of every covariance source, as `fit_region_stage` fits it in memory:
    conformal on the calibration part's true positives (`tps`, per part) under the fitted Σ'
    (gaussian without a calibration part, or with `auto` and fewer than `min_group` of them).
    The scores are computed part by part: only they, the classes and distances are whole."""
    if "x" not in opts.dims or "y" not in opts.dims:   # no ellipse to serve
        return dict.fromkeys(covs)
    method = "gaussian" if tps is None else opts.region_method
    return {source: region_fit_of_scores(
                None if tps is None else calibration_scores(tps, source, cov, classes,
                                                            opts.dims),
                len(classes), method, opts.min_group, opts.distance_edges,
                **opts.conformal_options())
            for source, cov in covs.items()}


def stream_covariance(classes: tuple[str, ...], source: str, firsts: list[FirstPass],
                      tps: list[CalibrationTPs] | None, opts: FitOptions) -> CovarianceFit:
    """The covariance stage of `source` as `fit_covariance_stage` fits it: with `auto`, each
    candidate (depth, shrinkage) fit on the training part's summed statistics and scored by
    the regression NLL of the calibration true positives (a mean over parts, weighted by
    their counts); the chosen one refit on the training part (conformal regions follow) or
    on the whole fit part."""
    method = opts.cov_method
    names = list(COV_METHODS) if method == "auto" else [method]
    if source == "none" or (method == "auto" and tps is None):
        names = ["depth"] if method == "auto" else names   # no Σ to shrink / nothing to choose
    train = _training_sums(firsts, source)
    candidates: dict[str, dict[str, float | None]] = {}
    if tps is not None and len(names) > 1:
        chosen, candidates = choose_lowest_nll(names, lambda name: {"nll": _held_out_nll(
            _binned_scaler(name, source, classes, *train, opts), tps, source, classes)})
    else:
        chosen = names[0]
    fit_on = train
    if tps is not None and opts.region_method == "gaussian":   # the whole fit part
        fit_on = tuple(a + b for a, b in zip(train, _calibration_sums(tps, source, classes,
                                                                       opts), strict=True))
    return covariance_fit(_binned_scaler(chosen, source, classes, *fit_on, opts), classes,
                          chosen, candidates)


def refit_covariance(classes: tuple[str, ...], source: str, firsts: list[FirstPass],
                     tps: list[CalibrationTPs], opts: FitOptions, method: str,
                     with_training: bool) -> CovarianceFit:
    """The `method` scaler of `source` fit on the calibration true positives' statistics,
    with the training part's added when `with_training` (the whole fit part)."""
    fit_on = _calibration_sums(tps, source, classes, opts)
    if with_training:
        fit_on = tuple(a + b for a, b in zip(_training_sums(firsts, source), fit_on,
                                             strict=True))
    return covariance_fit(_binned_scaler(method, source, classes, *fit_on, opts), classes,
                          method)


def _training_sums(firsts: list[FirstPass], source: str) -> tuple[BinSums, np.ndarray]:
    """The depth statistics and `near_zero_q` sums of the training part's true positives,
    summed over the parts' first passes."""
    return (reduce(add, (f.bins[source] for f in firsts)),
            sum(f.near_q[source] for f in firsts))


def _held_out_nll(scaler: Any, tps: list[CalibrationTPs], source: str,
                  classes: tuple[str, ...]) -> float | None:
    """The regression NLL of all calibration true positives under `scaler`, part by part
    (None when there are none or a Σ' is singular, as in memory)."""
    total, count = 0.0, 0
    for p in tps:
        if not len(p.labels):
            continue
        served = scaler.transform(p.covariances[source], p.distances,
                                  np.asarray(classes)[p.labels])
        nll = regression_nll_or_none(p.residuals, served)
        if nll is None:
            return None
        total, count = total + nll * len(p.labels), count + len(p.labels)
    return None if count == 0 else total / count


def _binned_scaler(name: str, source: str, classes: tuple[str, ...], total: BinSums,
                   near_q: np.ndarray, opts: FitOptions) -> Any:
    """The depth or shrinkage scaler fit on summed statistics (groups named and ordered as
    the in-memory fit names and orders them: by class name)."""
    groups, pooled = total.finish()
    present = sorted((classes[g], g) for g in np.flatnonzero(total.n > 0))
    keys, index = [name for name, _ in present], [g for _, g in present]
    try:
        with warnings.catch_warnings():   # s at a bound: Σ carries no (or all) information
            warnings.filterwarnings("ignore", "shrinkage s for class", RuntimeWarning)
            scaler = make_scaler(name, opts.min_samples)
            if name == "depth":
                return scaler.fit_binned([groups[g] for g in index], pooled, keys,
                                         len(opts.dims))
            return scaler.fit_binned([groups[g] for g in index], pooled, near_q[index], keys,
                                     len(opts.dims), has_sigma=source != "none")
    except ValueError as exc:
        raise ValueError(f"{name} covariance scaling failed with cov_source={source!r}: {exc}"
                         ) from exc


def _calibration_sums(tps: list[CalibrationTPs], source: str, classes: tuple[str, ...],
                      opts: FitOptions) -> tuple[BinSums, np.ndarray]:
    """The depth statistics and `near_zero_q` sums of the calibration true positives, built
    part by part (the sums add)."""
    n_classes = len(classes)
    bins, near = BinSums.build_empty(len(opts.dims), n_classes), np.zeros(n_classes)
    for p in tps:
        if len(p.labels):
            terms = fit_inputs(p.residuals, p.covariances[source], p.distances, p.labels)[5]
            bins = bins + BinSums.build(terms, p.labels, n_classes)
            near = near + near_zero_q(terms, p.labels, n_classes)
    return bins, near
