"""calibrators.monitoring: no alarm on in-distribution feedback, a quick one under a shift."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.monitoring import AlarmRule, DriftMonitor, collect_evidence
from tests.calibrators.drift_rate import one_run


def test_in_distribution_feedback_raises_no_alarm_in_2000_frames_and_a_shift_one_fast():
    run = one_run(0, frames=2000, shift=4.0, shifted_frames=100)
    assert run.false_alarm_frame is None
    assert run.detection_frame is not None and run.detection_frame <= 40


def test_state_round_trips_and_alarms_are_kept_once(tmp_path):
    from calibrators import FitOptions, fit_profile
    from calibrators.data import DEFAULT_DEPTH_K, synthetic_dump

    profile = fit_profile(synthetic_dump(n_frames=120, seed=3), FitOptions(holdout=0.3))
    bad = collect_evidence(synthetic_dump(n_frames=60, seed=4, depth_k={
        k: 8 * v for k, v in DEFAULT_DEPTH_K.items()}), profile)
    mon = DriftMonitor.for_evidence(bad)
    first = mon.update(bad)
    assert first and all(a["kind"] == "region" for a in first[:1])
    again = DriftMonitor.from_dict(mon.to_dict())
    assert again.frames == 60 and again.alarms == mon.alarms
    np.testing.assert_allclose(again.statistic()[1], mon.statistic()[1], atol=1e-5)
    assert again.update(bad) == [] or all(a["test"] not in {b["test"] for b in first}
                                          for a in again.alarms[len(first):])


def test_the_threshold_grows_with_tests_horizon_and_confidence():
    rule = AlarmRule()
    assert rule.log_threshold(320) == pytest.approx(np.log(320 * 2000 / 0.01))
    with pytest.raises(ValueError, match="false_alarm"):
        AlarmRule(false_alarm=0.0)
