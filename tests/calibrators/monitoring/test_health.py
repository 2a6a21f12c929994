"""calibrators.monitoring: feedback evidence equals the offline summary on the same frames."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators import FitOptions, fit_profile, summarize
from calibrators.data import select_detections, synthetic_dump
from calibrators.monitoring import HealthCounts, collect_evidence, health_figures


@pytest.fixture(scope="module")
def profile():
    return fit_profile(synthetic_dump(n_frames=120, seed=1), FitOptions(holdout=0.3))


@pytest.fixture(scope="module")
def feedback():
    return synthetic_dump(n_frames=40, seed=2)


def test_figures_equal_the_summary_of_the_same_frames(profile, feedback):
    ev = collect_evidence(feedback, profile)
    fig = health_figures(ev.counts(), profile.classes, ev.levels, ev.distance_edges)
    s = summarize(feedback, profile).to_dict()
    assert fig["ece"]["value"] == pytest.approx(s["classification"]["ece"]["after"])
    assert fig["tp"] == s["counts"]["tp"] and fig["frames"] == 40
    assert [o["coverage"] for o in fig["coverage"]["overall"]] == pytest.approx(
        s["regions"]["coverage"]["overall"])
    offline = {(r["class"], r["bin"]): r for r in s["regions"]["coverage"]["rows"]}
    assert len(fig["coverage"]["cells"]) == len(offline)
    for row in s["per_class"]:
        assert fig["classwise_ece"][row["class"]] == pytest.approx(row["ece_after"])


def test_sums_over_frames_add_and_subtract(profile, feedback):
    ev = collect_evidence(feedback, profile)
    whole, head, tail = ev.counts(), ev.counts(0, 15), ev.counts(15)
    both = head + tail
    assert both.frames == whole.frames == 40
    np.testing.assert_allclose(both.region_hits, whole.region_hits)
    back = HealthCounts.from_dict(whole.to_dict()) - tail
    np.testing.assert_allclose(back.score_sum, head.score_sum)
    assert back.ece() == pytest.approx(head.ece())


def test_bounds_hold_the_figure_and_empty_sums_have_none(profile, feedback):
    ev = collect_evidence(feedback, profile)
    fig = health_figures(ev.counts(0, 3), profile.classes, ev.levels, ev.distance_edges)
    assert fig["ece"]["lower"] <= fig["ece"]["value"] <= fig["ece"]["upper"]
    for lvl in fig["coverage"]["overall"]:
        assert lvl["lower"] <= lvl["coverage"] <= lvl["upper"]
    empty = health_figures(ev.counts(0, 0), profile.classes, ev.levels, ev.distance_edges)
    assert empty["ece"] == {"value": None, "lower": None, "upper": None}
    assert empty["coverage"]["cells"] == [] and empty["coverage"]["overall"][0]["n"] == 0


def test_frames_without_detections_count_their_ground_truth(profile, feedback):
    none = select_detections(feedback, np.zeros(feedback.n_detections, dtype=bool))
    ev = collect_evidence(none, profile)
    assert ev.counts().detections == 0 and ev.counts().gt == len(feedback.gt_labels)


def test_a_dump_of_other_classes_is_refused(profile):
    with pytest.raises(ValueError, match="classes"):
        collect_evidence(synthetic_dump(n_frames=2, classes=("car", "bus")), profile)
