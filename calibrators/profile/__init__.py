"""A fitted calibration profile and everything that applies it.

- `_profile`: `CalibrationProfile`, the versioned, JSON-stored result of a fit.
- `_serialise`: the profile's JSON fields, checked on load (score stage, per-source stages).
- `_detections`: `Detections`, the one batch type at the calibrate boundary (arrays [N], frame
  ids, rows, user ids) with its adapters from a dump, JSON records and nuScenes boxes.
- `_calibrate`: the calibration of a batch — scores, scaled covariances, ellipses, regions —
  into `CalibratedDetections`.
- `_apply`: `apply_profile(dump, profile)`, the same for a whole dump.
- `_read`: `read_profile(text)`, a stored profile of any kind (3-D, or a 2-D `Profile2D`).
"""

from calibrators.profile._apply import apply_profile, check_profile_fits
from calibrators.profile._calibrate import CalibratedDetections, calibrate_detections
from calibrators.profile._detections import (
    WIRE_NAMES,
    Detections,
    box9,
    calibrated_records,
    detections_from_records,
    ellipses_json,
    label_index,
    unbounded_none,
)
from calibrators.profile._profile import CalibrationProfile, make_provenance
from calibrators.profile._read import read_profile
from calibrators.profile._serialise import SourceStage, score_stage, source_stage

__all__ = ["WIRE_NAMES", "CalibratedDetections", "CalibrationProfile", "Detections",
           "SourceStage", "apply_profile", "box9", "calibrate_detections", "calibrated_records",
           "check_profile_fits", "detections_from_records", "ellipses_json",
           "label_index", "make_provenance", "read_profile", "score_stage", "source_stage",
           "unbounded_none"]
