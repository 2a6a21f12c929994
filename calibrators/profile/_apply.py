"""Apply a profile to a whole dump: `apply_profile(dump, profile) -> CalibratedDetections`.

The dump's detections go through the one calibrate batch, `Detections.from_dump`: every
decoder layer's logits (modulation uses them; the final layer is the last), the final boxes,
the raw Σ of the profile's covariance source (`source_arrays`) and each detection's ego
position; the result keeps each detection's identity (frame token and dump row).
"""

from __future__ import annotations

from collections.abc import Sequence

from calibrators.core.defaults import ELLIPSE_CONFIDENCE
from calibrators.covariance import resolve_cov_source, source_arrays
from calibrators.data import Dump
from calibrators.profile._calibrate import CalibratedDetections
from calibrators.profile._detections import Detections
from calibrators.profile._profile import CalibrationProfile

__all__ = ["apply_profile", "check_profile_fits", "source_arrays"]


def check_profile_fits(dump: Dump, profile: CalibrationProfile) -> None:
    """Raise ValueError unless `profile` can calibrate `dump`: the same classes in the same
    order and score mode, and the covariance source the profile was fit with."""
    if tuple(profile.classes) != tuple(dump.classes) or profile.score_mode != dump.score_mode:
        raise ValueError(f"profile is for {profile.score_mode} classes {list(profile.classes)} "
                         f"but the dump has {dump.score_mode} classes {list(dump.classes)}")
    resolve_cov_source(dump, profile.cov_source, tuple(profile.cov_dims))


def apply_profile(dump: Dump, profile: CalibrationProfile, *,
                  ellipse_confidence: float = ELLIPSE_CONFIDENCE,
                  levels: Sequence[float] | None = None) -> CalibratedDetections:
    """Calibrate the N final-layer detections of `dump` with `profile` (arrays [N], in the
    dump's detection order), with regions at `levels`; see `calibrators.profile._calibrate` for the
    result's fields."""
    check_profile_fits(dump, profile)
    return Detections.from_dump(dump, profile.cov_source).calibrate(
        profile, ellipse_confidence=ellipse_confidence, levels=levels)
