"""Calibration metrics for detection scores and box uncertainty (thesis section 2.7).

Every function validates its input and raises ValueError naming the argument and the
reason. Result objects are frozen dataclasses with `to_dict()` (JSON-able, NaN -> None).
"""

from calibrators.metrics.classification import (
    ReliabilityDiagram,
    expected_calibration_error,
    max_calibration_error,
    reliability_diagram,
)
from calibrators.metrics.curves import (
    CalibrationCurve,
    average_calibration_curve,
    miscalibration_area,
)
from calibrators.metrics.detection import detection_ece
from calibrators.metrics.intervals import (
    INTERVAL_CONFIDENCE,
    coverage_allowance,
    proportion_bounds,
)
from calibrators.metrics.localisation import LAECE_BINS, LocalisationECE, localisation_ece
from calibrators.metrics.regions import (
    CoverageTable,
    EllipseCoverage,
    classwise_ece,
    coverage_table,
    ellipse_coverage,
    mean_ellipse_area,
)
from calibrators.metrics.regression import (
    Coverage,
    ResidualPlot,
    coverage,
    expected_mahalanobis,
    mahalanobis,
    regression_nll,
    residual_uncertainty,
)
from calibrators.metrics.scoring import brier_score, classification_nll

__all__ = [
    "INTERVAL_CONFIDENCE",
    "LAECE_BINS",
    "CalibrationCurve",
    "Coverage",
    "CoverageTable",
    "EllipseCoverage",
    "LocalisationECE",
    "ReliabilityDiagram",
    "ResidualPlot",
    "average_calibration_curve",
    "brier_score",
    "classification_nll",
    "classwise_ece",
    "coverage",
    "coverage_allowance",
    "coverage_table",
    "detection_ece",
    "ellipse_coverage",
    "expected_calibration_error",
    "expected_mahalanobis",
    "localisation_ece",
    "mahalanobis",
    "max_calibration_error",
    "mean_ellipse_area",
    "miscalibration_area",
    "proportion_bounds",
    "regression_nll",
    "reliability_diagram",
    "residual_uncertainty",
]
