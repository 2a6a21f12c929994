"""Cross-fitted conformal radii (`FitOptions.region_calibration='cross'`): every fit true
positive calibrates, each part scored under the Σ' fit on the other; the radii are served with
the Σ' fit on the whole fit part. Split profiles are unchanged, old ones serve as before, and
the streamed fit reproduces it (tests/calibrators/fit/test_fit_stream.py).

The world of the coverage tests: synthetic cars and buses whose near-range buses (0-15 m, a
rare cell: about 40 true positives in 400 val frames) have 1.6 times wider residuals than
the rest."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibrators import (
    CalibrationProfile,
    FitOptions,
    OptionError,
    apply_profile,
    fit_profile,
    match_dump,
    tp_residuals,
)
from calibrators.data import Dump, synthetic_dump
from calibrators.regions import xy_mahalanobis

CLASSES = ("car", "bus")
WIDE = 1.6
Q = 0.9
RARE = {"other_sources": False, "cov_source": "given", "min_group": 40}


def _widened(dump: Dump) -> Dump:
    """`dump` with the residuals of its near-range (< 15 m) bus true positives, in every
    decoder layer, `WIDE` times wider."""
    m = match_dump(dump)
    tp = np.flatnonzero(m.tp)
    rows = tp[(dump.det_labels[tp] == 1) & (dump.det_distance[tp] < 15)]
    boxes = dump.det_boxes.copy()
    gt = dump.gt_boxes[m.gt_index[rows], :2][:, None, :]
    boxes[rows, :, :2] = gt + WIDE * (boxes[rows, :, :2] - gt)
    return replace(dump, det_boxes=boxes)


def _rare(seed: int, n_frames: int = 400) -> Dump:
    return _widened(synthetic_dump(n_frames=n_frames, classes=CLASSES, seed=seed))


@pytest.fixture(scope="module")
def test_cell():
    """The test dump, its matching, and its true positives' rare-cell mask."""
    test = _rare(99, n_frames=2000)
    m = match_dump(test)
    cell = (test.det_labels[m.tp] == 1) & (test.det_distance[m.tp] < 15)
    return test, m, cell


def _rare_cell(profile: CalibrationProfile) -> dict:
    return next(r for r in profile.report["selection"]["regions"]["cells"]
                if r["class"] == "bus" and r["bin"] == 0)


def _cell_coverage(profile: CalibrationProfile, test_cell) -> tuple[float, float]:
    """(coverage at Q of the rare cell's test true positives, its served radius)."""
    test, m, cell = test_cell
    out = apply_profile(test, profile, levels=[Q])
    md = xy_mahalanobis(tp_residuals(test, m), out.covariances[m.tp], ("x", "y"))
    radii = out.region_radii[Q][m.tp][cell]
    return float((md[cell] <= radii).mean()), float(radii[0])


def test_every_fit_true_positive_calibrates_and_sigma_is_fit_on_all():
    val = synthetic_dump(n_frames=120, seed=5)
    cross = fit_profile(val, cov_source="given", cov_method="shrinkage",
                        region_calibration="cross")
    split = fit_profile(val, cov_source="given", cov_method="shrinkage",
                        region_calibration="split")
    on_all = fit_profile(val, cov_source="given", cov_method="shrinkage",
                         region_method="gaussian")
    selection = cross.report["selection"]["regions"]
    assert selection["calibration"] == "cross" and cross.regions["calibration"] == "cross"
    assert selection["calibration_tps"] == int(match_dump(val).tp.sum())
    assert split.report["selection"]["regions"]["calibration_tps"] < selection[
        "calibration_tps"]
    assert cross.depth_k == on_all.depth_k and cross.depth_k != split.depth_k
    assert cross.covariance_scaling == on_all.covariance_scaling
    assert cross.score_calibration == split.score_calibration
    for stage in cross.sources.values():   # every covariance source is cross-fitted
        assert stage["regions"]["calibration"] == "cross"


def test_the_rare_cell_is_covered_over_seeded_draws(test_cell):
    """Over val draws and their seeded splits, the rare cell's coverage is q on average, and
    all its val true positives stand behind its radius."""
    coverage = []
    for seed in range(8):
        val = _rare(seed)
        profile = fit_profile(val, FitOptions(seed=seed, region_calibration="cross", **RARE))
        m = match_dump(val)
        n_cell = int(((val.det_labels[m.tp] == 1) & (val.det_distance[m.tp] < 15)).sum())
        assert _rare_cell(profile)["count"] == n_cell
        coverage.append(_cell_coverage(profile, test_cell)[0])
    assert np.mean(coverage) >= Q - 0.02, coverage


def test_cross_radii_move_less_with_the_split_seed(test_cell):
    """One val dump, six calibration-split seeds: the rare cell's radius moves much less when
    every frame calibrates."""
    val = _rare(3)
    spread = {}
    for calibration in ("split", "cross"):
        radii = [_cell_coverage(fit_profile(val, FitOptions(
            seed=s, region_calibration=calibration, **RARE)), test_cell)[1] for s in range(6)]
        spread[calibration] = float(np.std(radii))
    assert spread["cross"] < 0.5 * spread["split"], spread


def test_split_profiles_are_as_before_and_cross_profiles_round_trip():
    val, test = synthetic_dump(n_frames=100, seed=7), synthetic_dump(n_frames=40, seed=8)
    split = fit_profile(val, cov_source="given", region_calibration="split")
    assert set(split.regions) == {"method", "conformal"}   # what earlier versions wrote
    assert "calibration" not in split.report["selection"]["regions"]
    old = split.to_dict()
    old["provenance"]["options"].pop("region_calibration")   # a profile from before it
    loaded = CalibrationProfile.from_dict(old)
    for profile in (split, fit_profile(val, cov_source="given", region_calibration="cross")):
        again = CalibrationProfile.from_json(profile.to_json())
        assert again == profile
        a, b = apply_profile(test, profile, levels=[0.9]), apply_profile(test, again,
                                                                         levels=[0.9])
        np.testing.assert_array_equal(a.region_radii[0.9], b.region_radii[0.9])
    np.testing.assert_array_equal(apply_profile(test, loaded, levels=[0.9]).region_radii[0.9],
                                  apply_profile(test, split, levels=[0.9]).region_radii[0.9])


def test_a_bad_value_names_the_option():
    with pytest.raises(OptionError) as info:
        FitOptions(region_calibration="jackknife")
    assert info.value.field == "region_calibration"
