"""detcal calibration library: numpy + scipy only (no torch, no server).

Fit a temperature for the class logits and one depth-scaling factor per class for the box
covariance on a validation dump, store them as a `CalibrationProfile`, apply it to new
detections. See docs/science.md for the math and docs/formats.md for the dump formats.

The spine every front end goes through (service, CLI, dashboard, report):

    profile = fit_profile(dump, FitOptions(holdout=0.3))   # fit
    out = apply_profile(dump, profile)                      # apply -> CalibratedDetections
    out = Detections.from_dump(dump, profile.cov_source).calibrate(profile)   # the same
    summary = summarize(dump, profile)                      # before/after -> Summary

and, for the arrays in between, `match_dump`, `tp_residuals`, `raw_covariances`.
"""

from calibrators import io, metrics
from calibrators.apply import apply_profile, check_profile_fits
from calibrators.covariance import layer_spread
from calibrators.depth import DepthScaler
from calibrators.detections import Detections
from calibrators.dump import Dump
from calibrators.ellipse import Ellipse, ellipse
from calibrators.evaluate import EvaluationReport, evaluate
from calibrators.exceptions import NotFittedError
from calibrators.fit import fit_profile
from calibrators.io import load_dump, load_nuscenes, save_dump, save_nuscenes
from calibrators.matched import match_dump, raw_covariances, resolve_cov_source, tp_residuals
from calibrators.matching import MatchResult, match
from calibrators.options import FitOptions, OptionError
from calibrators.profile import CalibratedDetections, CalibrationProfile
from calibrators.summary import format_table, summarize
from calibrators.summary_types import ProfileReport, Summary
from calibrators.temperature import TemperatureScaler

__all__ = [
    "CalibratedDetections",
    "CalibrationProfile",
    "DepthScaler",
    "Detections",
    "Dump",
    "Ellipse",
    "EvaluationReport",
    "FitOptions",
    "MatchResult",
    "NotFittedError",
    "OptionError",
    "ProfileReport",
    "Summary",
    "TemperatureScaler",
    "apply_profile",
    "check_profile_fits",
    "ellipse",
    "evaluate",
    "fit_profile",
    "format_table",
    "io",
    "layer_spread",
    "load_dump",
    "load_nuscenes",
    "match",
    "match_dump",
    "metrics",
    "raw_covariances",
    "resolve_cov_source",
    "save_dump",
    "save_nuscenes",
    "summarize",
    "tp_residuals",
]
