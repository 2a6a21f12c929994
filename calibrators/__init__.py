"""detcal calibration library: numpy, scipy and pyarrow (for Parquet and Arrow); no torch, no
server.

Fit a calibration profile on a validation dump: score calibration (temperature, per-class
temperature, Platt, isotonic or histogram binning), covariance scaling (depth scaling
`Σ + k·d·I`, or with shrinkage `s·Σ + k·d·I`) and coverage regions (Gaussian or split
conformal); store it as a `CalibrationProfile`, apply it to new detections. See
docs/science.md for the math and docs/formats.md for the dump formats.

The spine every front end goes through (service, CLI, dashboard, report):

    profile = fit_profile(dump, FitOptions(holdout=0.3))   # fit
    out = apply_profile(dump, profile)                      # apply -> CalibratedDetections
    out = Detections.from_dump(dump, profile.cov_source).calibrate(profile)   # the same
    summary = summarize(dump, profile)                      # before/after -> Summary

and, for the arrays in between, `match_dump`, `tp_residuals`, `raw_covariances`. Every
estimator (`TemperatureScaler`, `ClassTemperatureScaler`, `PlattScaler`,
`IsotonicCalibrator`, `HistogramBinning`, `DepthScaler`, `ShrinkageDepthScaler`,
`ConformalRegions`) and every error (`FieldError`, `OptionError`, `NotFittedError`) is
exported here; the defaults (`ELLIPSE_CONFIDENCE`, `DEFAULT_LEVELS`, `MATCH_THRESHOLD`) too.
"""

from calibrators import io, metrics
from calibrators.core.defaults import DEFAULT_LEVELS, ELLIPSE_CONFIDENCE, MATCH_THRESHOLD
from calibrators.core.errors import FieldError, NotFittedError, OptionError
from calibrators.core.json_safe import to_jsonable
from calibrators.covariance import (
    DepthScaler,
    ShrinkageDepthScaler,
    layer_spread,
    raw_covariances,
    resolve_cov_source,
)
from calibrators.data import Dump
from calibrators.evaluation import (
    EvaluationReport,
    MatchResult,
    ProfileReport,
    Summary,
    evaluate,
    format_table,
    match,
    match_dump,
    summarize,
    tp_residuals,
)
from calibrators.fit import FitOptions, fit_profile
from calibrators.io import (
    ParquetDataset,
    ParquetWriter,
    load_dump,
    load_nuscenes,
    load_parquet,
    open_parquet,
    save_dump,
    save_nuscenes,
    save_parquet,
)
from calibrators.profile import (
    CalibratedDetections,
    CalibrationProfile,
    Detections,
    apply_profile,
    check_profile_fits,
)
from calibrators.regions import ConformalRegions, Ellipse, ellipse
from calibrators.scores import (
    ClassTemperatureScaler,
    HistogramBinning,
    IsotonicCalibrator,
    PlattScaler,
    TemperatureScaler,
)

__all__ = [
    "CalibratedDetections",
    "CalibrationProfile",
    "ClassTemperatureScaler",
    "ConformalRegions",
    "DEFAULT_LEVELS",
    "DepthScaler",
    "Detections",
    "Dump",
    "ELLIPSE_CONFIDENCE",
    "Ellipse",
    "EvaluationReport",
    "FieldError",
    "FitOptions",
    "HistogramBinning",
    "IsotonicCalibrator",
    "MATCH_THRESHOLD",
    "MatchResult",
    "NotFittedError",
    "OptionError",
    "ParquetDataset",
    "ParquetWriter",
    "PlattScaler",
    "ProfileReport",
    "ShrinkageDepthScaler",
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
    "load_parquet",
    "match",
    "match_dump",
    "metrics",
    "open_parquet",
    "raw_covariances",
    "resolve_cov_source",
    "save_dump",
    "save_nuscenes",
    "save_parquet",
    "summarize",
    "to_jsonable",
    "tp_residuals",
]
