"""Monitoring: how a served profile keeps its calibration claims on labelled feedback.

- calibration health (`_health`): the evidence of feedback frames (`collect_evidence`,
  `FrameEvidence`), summed per class and distance group (`HealthCounts`) and turned into
  coverage and ECE figures with their confidence bounds (`health_figures`).
- drift (`_drift`): sequential tests on that evidence that raise an alarm when the served
  scores or regions stop holding (`DriftMonitor`, `AlarmRule`).
"""

from calibrators.monitoring._drift import (
    REGION_FRACTIONS,
    SCORE_LAMBDAS,
    AlarmRule,
    DriftMonitor,
)
from calibrators.monitoring._health import (
    BOUND_CONFIDENCE,
    HEALTH_LEVELS,
    N_SCORE_BINS,
    FrameEvidence,
    HealthCounts,
    RegionGroups,
    check_feedback,
    collect_evidence,
    feedback_source,
    health_figures,
    profile_edges,
    region_groups,
)

__all__ = ["BOUND_CONFIDENCE", "HEALTH_LEVELS", "N_SCORE_BINS", "REGION_FRACTIONS",
           "SCORE_LAMBDAS", "AlarmRule", "DriftMonitor", "FrameEvidence", "HealthCounts",
           "RegionGroups", "check_feedback", "collect_evidence", "feedback_source",
           "health_figures", "profile_edges", "region_groups"]
