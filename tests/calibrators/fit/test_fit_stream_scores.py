"""The streamed score stage: every per-class candidate fit on the training part's table,
chosen on the calibration part's, refit on both. Up to `EXACT_ROWS` detections it is the
in-memory stage (served scores equal to 1e-6: a temperature is searched to its Brent tolerance
on sums taken in another order); above, on the cell counts, every candidate's
held-out NLL stays within 1e-4 of the in-memory one."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.data import synthetic_dump
from calibrators.fit import fit_profile, fit_profile_stream
from calibrators.io import load_parquet, save_parquet
from calibrators.profile import apply_profile
from tests.calibrators.fit.test_fit_stream import assert_close_tree


def fit_both(tmp_path, dump, rows_per_part=170, exact_rows=1 << 20, **options):
    save_parquet(tmp_path / "ds", dump, rows_per_part=rows_per_part)
    loaded = load_parquet(tmp_path / "ds")
    return (fit_profile_stream(tmp_path / "ds", exact_rows=exact_rows, **options),
            fit_profile(loaded, **options), loaded)


def served_scores(profile, dump):
    return apply_profile(dump, profile).scores


@pytest.mark.parametrize("mode, options", [
    ("sigmoid", {}),                                           # the defaults: auto, κ chosen
    ("sigmoid", {"modulation": True, "holdout": 0.2, "min_score": 0.05}),
    ("sigmoid", {"score_method": "platt_range", "score_shrink": 30.0}),
    ("softmax", {"score_method": "isotonic", "seed": 5}),
    ("softmax", {"score_method": "histogram", "calibration": 0.0}),   # no calibration part
    ("sigmoid", {"score_method": "class_temperature", "min_group": 10_000}),
])
def test_streamed_scores_equal_the_in_memory_ones(tmp_path, mode, options):
    dump = synthetic_dump(n_frames=80, n_gt_per_frame=12, score_mode=mode, seed=31)
    streamed, in_memory, loaded = fit_both(tmp_path, dump, **options)
    assert streamed.score_method == in_memory.score_method
    assert_close_tree(streamed.report["selection"]["score"],
                      in_memory.report["selection"]["score"], "score", rel=1e-6)
    assert np.abs(served_scores(streamed, loaded) - served_scores(in_memory, loaded)).max() \
        < 1e-6
    assert_close_tree(streamed.regions, in_memory.regions, "regions")


def test_the_score_stage_is_the_same_whatever_the_partitioning(tmp_path):
    dump = synthetic_dump(n_frames=50, n_gt_per_frame=10, seed=32)
    scores = []
    for rows in (90, 400, 10_000):
        save_parquet(tmp_path / f"ds{rows}", dump, rows_per_part=rows)
        profile = fit_profile_stream(tmp_path / f"ds{rows}", score_method="isotonic")
        scores.append(served_scores(profile, dump))
    for other in scores[1:]:
        assert np.abs(other - scores[0]).max() < 1e-12


def test_the_cell_counts_of_a_large_fit_choose_as_the_rows_do(tmp_path):
    """Above `exact_rows` the stage fits on the tables' cell counts: the candidates' held-out
    NLL moves by < 1e-4, the choice and κ stay, and served scores move by little."""
    dump = synthetic_dump(n_frames=120, n_gt_per_frame=15, seed=33)
    streamed, in_memory, loaded = fit_both(tmp_path, dump, rows_per_part=400, exact_rows=0)
    got, want = (p.report["selection"]["score"] for p in (streamed, in_memory))
    assert got["chosen"] == want["chosen"] and got["shrink"] == want["shrink"]
    for name, cand in want["candidates"].items():
        assert got["candidates"][name]["nll"] == pytest.approx(cand["nll"], abs=1e-4), name
    diff = np.abs(served_scores(streamed, loaded) - served_scores(in_memory, loaded))
    assert diff.mean() < 1e-3


def test_progress_stages_are_those_of_the_in_memory_fit(tmp_path):
    dump = synthetic_dump(n_frames=30, n_gt_per_frame=8, seed=34)
    save_parquet(tmp_path / "ds", dump, rows_per_part=200)
    stages: dict[str, list[str]] = {"stream": [], "memory": []}
    fit_profile_stream(tmp_path / "ds", holdout=0.2, other_sources=False,
                       progress=lambda stage, fraction: stages["stream"].append(stage))
    fit_profile(load_parquet(tmp_path / "ds"), holdout=0.2, other_sources=False,
                progress=lambda stage, fraction: stages["memory"].append(stage))
    assert stages["stream"] == stages["memory"]
