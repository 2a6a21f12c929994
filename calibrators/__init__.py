"""detcal calibration library: numpy + scipy only (no torch, no server).

Fit a temperature for the class logits and one depth-scaling factor per class for the box
covariance on a validation dump, store them as a `CalibrationProfile`, apply it to new
detections. See docs/science.md for the math and docs/formats.md for the dump formats.
"""

from calibrators import io, metrics
from calibrators.covariance import layer_spread
from calibrators.depth import DepthScaler
from calibrators.dump import Dump
from calibrators.ellipse import Ellipse, ellipse
from calibrators.evaluate import EvaluationReport, evaluate
from calibrators.exceptions import NotFittedError
from calibrators.fit import fit_profile
from calibrators.io import load_dump, load_nuscenes, save_dump, save_nuscenes
from calibrators.matching import MatchResult, match
from calibrators.profile import CalibratedDetections, CalibrationProfile
from calibrators.temperature import TemperatureScaler

__all__ = [
    "CalibratedDetections",
    "CalibrationProfile",
    "DepthScaler",
    "Dump",
    "Ellipse",
    "EvaluationReport",
    "MatchResult",
    "NotFittedError",
    "TemperatureScaler",
    "ellipse",
    "evaluate",
    "fit_profile",
    "io",
    "layer_spread",
    "load_dump",
    "load_nuscenes",
    "match",
    "metrics",
    "save_dump",
    "save_nuscenes",
]
