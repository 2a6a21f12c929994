"""Cross-fitted conformal radii (`FitOptions.region_calibration='cross'`): calibrated on every
fit true positive instead of the calibration part's alone.

Split conformal calibrates the radii on the calibration part's scores under the `Σ'` fit on
the training part, so half of the val scenes never calibrate, and which half does moves a
rare class's coverage by several points (its residuals are correlated within a scene). With
two parts A (training) and B (calibration), K = 2 cross-fitting scores B under the `Σ'` fit
on A and A under the `Σ'` fit on B (the same covariance method, chosen as before on A and
B), pools the two sets of out-of-fold scores, fits `ConformalRegions` on the pool with the
same options, and serves the radii with the `Σ'` fit on the whole fit part. Every score is
out of fold, but the served `Σ'` is not the one any score was computed under, so the
finite-sample guarantee of split conformal becomes an approximation (cross-conformal: the
served `Σ'` is fit on twice the data of either fold's).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calibrators.data import Dump
from calibrators.evaluation import MatchResult
from calibrators.fit._options import FitOptions
from calibrators.fit._region_stage import (
    CovarianceFit,
    RegionFit,
    fit_covariance_stage,
    region_fit_of_scores,
    tp_scores,
)
from calibrators.profile import CalibrationProfile, apply_profile

__all__ = ["cross_fit_regions", "with_covariance"]

Part = tuple[Dump, MatchResult]


def with_covariance(profile: CalibrationProfile, cov: CovarianceFit) -> CalibrationProfile:
    """`profile` whose own covariance stage is `cov` (k, s per class and pooled)."""
    return replace(profile, depth_k=cov.depth_k, pooled_k=cov.pooled_k,
                   fallback_classes=cov.fallback_classes,
                   covariance_scaling={"method": cov.method, "scale": cov.scale,
                                       "pooled_scale": cov.pooled_scale})


def cross_fit_regions(profile: CalibrationProfile, cov: CovarianceFit, fit_all: Part,
                      train: Part, calib: Part, opts: FitOptions, method: str
                      ) -> tuple[CovarianceFit, RegionFit]:
    """The served covariance stage (fit on `fit_all`, with `cov`'s candidates) and the
    cross-fitted region stage (module docstring) of `profile`'s covariance source, where
    `profile` serves `cov`, the `Σ'` fit on `train`; `method`: the region method (auto,
    conformal) as `fit_region_stage` reads it, on the pooled true positives."""
    dims, source = tuple(opts.dims), profile.cov_source
    on_calib = fit_covariance_stage(calib, calib, None, dims, source, cov.method,
                                    opts.min_samples)
    scored = [tp_scores(calib, apply_profile(calib[0], profile).covariances, dims),
              tp_scores(train, apply_profile(train[0], with_covariance(profile, on_calib)
                                             ).covariances, dims)]
    pooled = tuple(np.concatenate(arrays) for arrays in zip(*scored, strict=True))
    region = region_fit_of_scores(pooled, len(profile.classes), method, opts.min_group,
                                  opts.distance_edges, **opts.conformal_options(),
                                  calibration="cross")
    served = fit_covariance_stage(fit_all, train, None, dims, source, cov.method,
                                  opts.min_samples)
    return replace(served, candidates=cov.candidates), region
