"""The streamed fit of a Parquet dataset equals `fit_profile` on the same data in memory (T
and every k to 1e-6 relative), refuses what it cannot reproduce, and merges exactly."""

from __future__ import annotations

import numpy as np
import pytest

# `SUBSAMPLE_MIN` and `_SUBSAMPLE_ROWS`, patched below, are globals of these private modules read
# at call time: the modules are imported for that alone (allowed in tests/test_imports.py).
import calibrators.fit._stream as fit_stream
import calibrators.scores._temperature as temperature
from calibrators.core.errors import OptionError
from calibrators.covariance import BinSums, depth_bins, fit_inputs
from calibrators.data import synthetic_dump
from calibrators.fit import FitOptions, check_stream_options, fit_profile, fit_profile_stream
from calibrators.io import load_parquet, save_parquet
from calibrators.scores import SIGMOID_BINS, SigmoidBins

THESIS = {"score_method": "temperature", "cov_method": "depth", "region_method": "gaussian"}


def assert_same_profile(streamed, in_memory, rel=1e-6):
    assert streamed.temperature == pytest.approx(in_memory.temperature, rel=rel)
    assert streamed.depth_k.keys() == in_memory.depth_k.keys()
    for c, k in in_memory.depth_k.items():
        assert streamed.depth_k[c] == pytest.approx(k, rel=rel), c
    assert streamed.pooled_k == pytest.approx(in_memory.pooled_k, rel=rel)
    assert streamed.fallback_classes == in_memory.fallback_classes
    assert (streamed.cov_source, streamed.schema_version) == (in_memory.cov_source,
                                                              in_memory.schema_version)
    assert (streamed.sources is None) == (in_memory.sources is None)
    for source, stage in (in_memory.sources or {}).items():
        for c, k in stage["depth_k"].items():
            assert streamed.sources[source]["depth_k"][c] == pytest.approx(k, rel=rel)
        # conformal radii are order statistics of scores under k, which Brent finds to 1e-6
        assert_close_tree(streamed.sources[source]["regions"], stage["regions"], source)
    counts = ("n_frames", "n_detections", "n_ground_truth", "n_fit_frames",
              "n_fit_detections", "n_holdout_frames", "n_matched", "options")
    assert {k: streamed.provenance[k] for k in counts} == {k: in_memory.provenance[k]
                                                           for k in counts}


def fit_both(tmp_path, dump, rows_per_part=150, **options):
    save_parquet(tmp_path / "ds", dump, rows_per_part=rows_per_part)
    loaded = load_parquet(tmp_path / "ds")
    return (fit_profile_stream(tmp_path / "ds", **options),
            fit_profile(loaded, dump_sha256="x", **options))


@pytest.mark.parametrize("mode, options", [
    ("sigmoid", {"holdout": 0.2, **THESIS}),
    ("sigmoid", {"calibration": 0.0, "cov_source": "layers", "dims": ("x", "y", "yaw")}),
    ("softmax", {"min_score": 0.05, "holdout": 0.1, "seed": 3, **THESIS}),
    ("softmax", {"modulation": True, "calibration": 0.0, "other_sources": False}),
])
def test_streamed_fit_equals_the_in_memory_fit(tmp_path, mode, options):
    dump = synthetic_dump(n_frames=60, n_gt_per_frame=12, score_mode=mode, seed=8)
    streamed, in_memory = fit_both(tmp_path, dump, **options)
    assert_same_profile(streamed, in_memory)
    assert "sample" not in streamed.report   # everything fit the report's budget
    assert_close_tree(streamed.report, in_memory.report)   # the same report, to rounding


def assert_close_tree(a, b, path="report", rel=1e-6):
    """Equal JSON trees, floats to `rel` (T and k differ by their Brent tolerance)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for key in a:
            assert_close_tree(a[key], b[key], f"{path}/{key}", rel)
    elif isinstance(a, list):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_close_tree(x, y, f"{path}[{i}]", rel)
    elif isinstance(a, float) and isinstance(b, float):
        assert a == pytest.approx(b, rel=rel, abs=1e-12), path
    else:
        assert a == b, path


def test_binned_sigmoid_path_equals_the_in_memory_fit(tmp_path):
    dump = synthetic_dump(n_frames=360, n_gt_per_frame=100, seed=9, n_layers=1)
    assert dump.n_detections > SIGMOID_BINS   # the binned search is used
    streamed, in_memory = fit_both(tmp_path, dump, rows_per_part=20_000, calibration=0.0,
                                   other_sources=False)
    assert_same_profile(streamed, in_memory)
    assert streamed.temperature == pytest.approx(2.0, rel=0.02)


def test_subsampled_softmax_path_equals_the_in_memory_fit(tmp_path, monkeypatch):
    # the subsample bracket from 2,000 rows on (both fits read the threshold at call time)
    monkeypatch.setattr(temperature, "SUBSAMPLE_MIN", 2_000)
    monkeypatch.setattr(fit_stream, "SUBSAMPLE_MIN", 2_000)
    monkeypatch.setattr(temperature, "_SUBSAMPLE_ROWS", 500)
    dump = synthetic_dump(n_frames=60, n_gt_per_frame=20, score_mode="softmax", seed=10)
    streamed, in_memory = fit_both(tmp_path, dump, rows_per_part=400, calibration=0.0)
    assert_same_profile(streamed, in_memory)


def test_report_summarises_a_bounded_sample_and_says_so(tmp_path):
    dump = synthetic_dump(n_frames=40, n_gt_per_frame=10, seed=11)
    save_parquet(tmp_path / "ds", dump, rows_per_part=100)
    profile = fit_profile_stream(tmp_path / "ds", holdout=0.25, report_detections=150,
                                 **THESIS)
    sample = profile.report["sample"]
    assert sample["fit"]["detections"] <= 150 < sample["fit"]["of_detections"]
    assert profile.report["fit"]["counts"]["detections"] == sample["fit"]["detections"]
    assert sample["holdout"]["frames"] <= sample["holdout"]["of_frames"] == 10


def test_auto_scores_on_softmax_are_refused(tmp_path):
    """The temperature candidate of softmax scores has no per-row statistic."""
    save_parquet(tmp_path / "ds", synthetic_dump(n_frames=10, seed=12, score_mode="softmax"))
    with pytest.raises(OptionError, match="cannot reproduce score_method='auto'") as err:
        fit_profile_stream(tmp_path / "ds")
    assert err.value.field == "score_method"


CONFORMAL = {"score_method": "temperature", "cov_method": "depth"}


@pytest.mark.parametrize("mode, options", [
    ("sigmoid", {**CONFORMAL, "region_method": "conformal", "min_group": 20}),
    ("sigmoid", {**CONFORMAL, "holdout": 0.2, "min_group": 15, "floor_delta": None}),
    ("softmax", {**CONFORMAL, "min_score": 0.05, "seed": 4, "region_method": "conformal",
                 "min_group": 10, "region_delta": 0.1, "cov_source": "layers"}),
    ("sigmoid", {**CONFORMAL, "min_group": 10_000}),   # auto with too few: gaussian
    ("sigmoid", {"score_method": "temperature", "min_group": 20}),   # cov auto, conformal
    ("softmax", {"score_method": "temperature", "cov_method": "shrinkage", "min_group": 15,
                 "holdout": 0.1}),
    ("sigmoid", {"score_method": "temperature", "region_method": "gaussian"}),   # auto, whole
    # cross-fitted radii: a second pass scores the training part under the calibration Σ'
    ("sigmoid", {**CONFORMAL, "region_method": "conformal", "min_group": 20,
                 "region_calibration": "cross"}),
    ("softmax", {"score_method": "temperature", "cov_method": "shrinkage", "min_group": 15,
                 "holdout": 0.1, "region_calibration": "cross", "cov_source": "layers"}),
    ("sigmoid", {"score_method": "temperature", "min_group": 20, "region_calibration": "cross",
                 "floor_delta": None}),
])
def test_streamed_conformal_regions_equal_the_in_memory_ones(tmp_path, mode, options):
    """The calibration part is drawn by frame token as in memory; the covariance candidates
    (depth, shrinkage) are fit on the training part's sums and chosen by the calibration true
    positives' NLL; the radii of every covariance source are fit on the same scores."""
    dump = synthetic_dump(n_frames=80, n_gt_per_frame=12, score_mode=mode, seed=9)
    streamed, in_memory = fit_both(tmp_path, dump, rows_per_part=170, **options)
    assert_same_profile(streamed, in_memory)
    assert streamed.provenance["n_calibration_frames"] == \
        in_memory.provenance["n_calibration_frames"] > 0
    assert streamed.region_method == in_memory.region_method
    # s: Brent on log s over an NLL that is flat where Σ says little (docs/science.md)
    assert_close_tree(streamed.covariance_scaling, in_memory.covariance_scaling, "scaling",
                      rel=1e-4)
    for source, stage in (in_memory.sources or {}).items():
        assert_close_tree(streamed.sources[source]["covariance_scaling"],
                          stage["covariance_scaling"], source, rel=1e-4)
    assert_close_tree(streamed.regions, in_memory.regions, "regions")
    assert_close_tree(streamed.report["selection"], in_memory.report["selection"], "selection")


def test_the_calibration_part_is_the_same_whatever_the_partitioning(tmp_path):
    dump = synthetic_dump(n_frames=50, n_gt_per_frame=10, seed=10)
    options = {**CONFORMAL, "region_method": "conformal", "min_group": 10}
    fits = []
    for rows in (90, 400, 10_000):
        save_parquet(tmp_path / f"ds{rows}", dump, rows_per_part=rows)
        fits.append(fit_profile_stream(tmp_path / f"ds{rows}", **options))
    # the same calibration true positives in every cell; radii equal up to the order in which
    # the parts' depth sums are added (k to rounding)
    assert len({str(f.regions["conformal"]["counts"]) for f in fits}) == 1
    for other in fits[1:]:
        assert_close_tree(other.regions, fits[0].regions, "regions")


def test_auto_means_the_thesis_methods_without_a_calibration_part():
    for mode in ("sigmoid", "softmax", None):
        check_stream_options(FitOptions(calibration=0.0), score_mode=mode)
        check_stream_options(FitOptions(), n_fit_frames=1, score_mode=mode)
    check_stream_options(FitOptions(), n_fit_frames=2, score_mode="sigmoid")
    with pytest.raises(OptionError):
        check_stream_options(FitOptions(), n_fit_frames=2, score_mode="softmax")


def test_data_errors_match_the_in_memory_messages(tmp_path):
    save_parquet(tmp_path / "ds", synthetic_dump(n_frames=10, seed=13, n_layers=1))
    with pytest.raises(ValueError, match="leaves no frame to fit on"):
        fit_profile_stream(tmp_path / "ds", holdout=0.99, **THESIS)
    with pytest.raises(OptionError, match="at least 2 decoder layers") as err:
        fit_profile_stream(tmp_path / "ds", modulation=True, **THESIS)
    assert err.value.field == "modulation"
    with pytest.raises(ValueError, match="no detection matched"):
        fit_profile_stream(tmp_path / "ds", threshold=1e-9, **THESIS)
    with pytest.raises(ValueError, match="leaves no detection"):
        fit_profile_stream(tmp_path / "ds", min_score=1.0, **THESIS)
    with pytest.raises(ValueError, match="is not a folder"):
        fit_profile_stream(tmp_path / "missing", **THESIS)


def test_bin_sums_of_chunks_add_up_to_the_whole():
    rng = np.random.default_rng(0)
    n = 3000
    r = rng.normal(size=(n, 2))
    a = rng.normal(size=(n, 2, 2))
    cov = a @ np.swapaxes(a, 1, 2) * np.exp(rng.uniform(-60, 5, n))[:, None, None]  # > 64 octaves
    d = rng.uniform(0.0, 50.0, n)
    d[:5] = 0.0
    codes = rng.integers(0, 4, n)
    terms = fit_inputs(r, cov, d, codes)[5]
    groups, pooled = depth_bins(terms, codes, 4)
    parts = np.array_split(rng.permutation(n), 3)
    total = None
    for rows in parts:
        part = BinSums.build(fit_inputs(r[rows], cov[rows], d[rows], codes[rows])[5],
                             codes[rows], 4)
        total = part if total is None else total + part
    total = total + BinSums.build_empty(2, 4)
    merged_groups, merged_pooled = total.finish()
    for x, y in zip([*groups, pooled], [*merged_groups, merged_pooled], strict=True):
        assert x.n == y.n and x.const == pytest.approx(y.const, rel=1e-12)
        assert np.array_equal(x.count, y.count)
        assert np.allclose(x.b_sum, y.b_sum, rtol=1e-12)
        assert np.allclose(x.a_mean, y.a_mean, rtol=1e-12)


def test_sigmoid_bins_of_chunks_add_up_and_coarsen():
    rng = np.random.default_rng(1)
    s = rng.standard_t(3, 50_000) * 3
    y = rng.integers(0, 2, 50_000)
    span = (float(s.min()), float(s.max()))
    whole = SigmoidBins.from_logits(s, y, 4096)
    parts = [SigmoidBins.from_logits(s[i::3], y[i::3], 4096, span=span) for i in range(3)]
    merged = parts[0] + parts[1] + parts[2]
    for t in (0.3, 1.0, 5.0):
        assert merged.objective()(np.log(t)) == pytest.approx(whole.objective()(np.log(t)),
                                                              rel=1e-12)
    coarse = whole.coarsen(64)
    direct = SigmoidBins.from_logits(s, y, 64)
    assert np.array_equal(coarse.count, direct.count)
    assert np.allclose(coarse.offset_sq, direct.offset_sq, rtol=1e-9)
    with pytest.raises(ValueError, match="different grids"):
        whole + direct


@pytest.mark.parametrize("damage", ["truncated", "overwritten"])
def test_a_corrupt_part_is_named(tmp_path, damage):
    from calibrators.core.errors import FieldError

    save_parquet(tmp_path / "ds", synthetic_dump(n_frames=20, seed=14), rows_per_part=200)
    part = sorted((tmp_path / "ds" / "detections").glob("*.parquet"))[1]
    data = part.read_bytes()
    part.write_bytes(data[:len(data) // 2] if damage == "truncated" else b"\0" * len(data))
    with pytest.raises(FieldError, match=f"detections/{part.name} is not a Parquet file"):
        fit_profile_stream(tmp_path / "ds")
