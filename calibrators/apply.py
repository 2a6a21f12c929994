"""Apply a profile to a whole dump: `apply_profile(dump, profile) -> CalibratedDetections`.

The one place that knows which of a dump's arrays a profile needs: every decoder layer's
logits (modulation uses them; the final layer is the last), the final boxes, the raw Σ of
the profile's covariance source (`given`: the dump's det_cov; `layers`: its per-layer
boxes; `hypotheses`: its det_hyp_boxes and det_hyp_scores) and each detection's ego position.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibrators.dump import Dump
from calibrators.matched import resolve_cov_source
from calibrators.profile import CalibratedDetections, CalibrationProfile

__all__ = ["apply_profile", "check_profile_fits", "source_arrays"]


def check_profile_fits(dump: Dump, profile: CalibrationProfile) -> None:
    """Raise ValueError unless `profile` can calibrate `dump`: the same classes in the same
    order and score mode, and the covariance source the profile was fit with."""
    if tuple(profile.classes) != tuple(dump.classes) or profile.score_mode != dump.score_mode:
        raise ValueError(f"profile is for {profile.score_mode} classes {list(profile.classes)} "
                         f"but the dump has {dump.score_mode} classes {list(dump.classes)}")
    resolve_cov_source(dump, profile.cov_source, tuple(profile.cov_dims))


def apply_profile(dump: Dump, profile: CalibrationProfile, *,
                  ellipse_confidence: float = 0.95,
                  levels: Sequence[float] | None = None) -> CalibratedDetections:
    """Calibrate the N final-layer detections of `dump` with `profile` (arrays [N], in the
    dump's detection order), with regions at `levels`; see `calibrators.serving` for the
    result's fields."""
    check_profile_fits(dump, profile)
    return profile.calibrate(
        layer_logits=dump.det_logits, labels=dump.det_label, boxes=dump.final_boxes,
        **source_arrays(dump, profile.cov_source),
        ego_xy=dump.ego_xy(dump.det_frame), ellipse_confidence=ellipse_confidence,
        levels=levels)


def source_arrays(dump: Dump, source: str) -> dict[str, np.ndarray | None]:
    """The keyword arguments of `CalibrationProfile.calibrate` that carry covariance `source`
    from `dump`: `covariances [N, D, D]` (given), `layer_boxes [N, L, 9]` (layers),
    `hyp_boxes [N, H, 9]` and `hyp_scores [N, H]` (hypotheses), nothing (none)."""
    if source == "given":
        return {"covariances": dump.det_cov}
    if source == "layers":
        return {"layer_boxes": dump.det_boxes}
    if source == "hypotheses":
        return {"hyp_boxes": dump.det_hyp_boxes, "hyp_scores": dump.det_hyp_scores}
    return {}
