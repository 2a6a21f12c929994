"""The streamed fit on a real 2-worker Dask LocalCluster (worker processes) equals the
in-memory fit; Dask specs are checked before anything starts."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.core.errors import FieldError
from calibrators.data import synthetic_dump
from calibrators.fit import Mapper, dask_client, fit_profile, fit_profile_stream, parse_dask_spec
from calibrators.io import load_parquet, save_parquet
from calibrators.profile import apply_profile

pytest.importorskip("distributed")


def test_dask_fit_on_two_worker_processes_equals_the_in_memory_fit(tmp_path):
    dump = synthetic_dump(n_frames=60, n_gt_per_frame=12, score_mode="softmax", seed=21)
    save_parquet(tmp_path / "ds", dump, rows_per_part=200)
    options = {"calibration": 0.0, "holdout": 0.2, "min_score": 0.02}
    in_memory = fit_profile(load_parquet(tmp_path / "ds"), **options)
    with dask_client("local:2") as client:
        assert len(client.scheduler_info()["workers"]) == 2
        streamed = fit_profile_stream(tmp_path / "ds", client=client, **options)
    assert streamed.temperature == pytest.approx(in_memory.temperature, rel=1e-6)
    for c, k in in_memory.depth_k.items():
        assert streamed.depth_k[c] == pytest.approx(k, rel=1e-6), c
    assert streamed.pooled_k == pytest.approx(in_memory.pooled_k, rel=1e-6)
    for source, stage in in_memory.sources.items():
        assert streamed.sources[source]["pooled_k"] == pytest.approx(stage["pooled_k"],
                                                                     rel=1e-6)
    assert streamed.fallback_classes == in_memory.fallback_classes


@pytest.mark.parametrize("spec, want", [("local", ("local", 2)), ("local:3", ("local", 3)),
                                        ("tcp://10.0.0.1:8786", ("address",
                                                                 "tcp://10.0.0.1:8786"))])
def test_dask_specs(spec, want):
    assert parse_dask_spec(spec) == want


@pytest.mark.parametrize("spec", ["", "local:0", "local:x", "10.0.0.1:8786", "http://x"])
def test_bad_dask_specs_are_refused_naming_dask(spec):
    with pytest.raises(FieldError, match="dask") as err:
        parse_dask_spec(spec)
    assert err.value.field == "dask"


def test_mapper_without_a_client_runs_here_in_order():
    assert Mapper().map(divmod, [7, 9], [2, 4]) == [(3, 1), (2, 1)]


def test_dask_default_fit_equals_the_in_memory_one(tmp_path):
    """With the default options (score candidates and κ chosen on the calibration part,
    covariance `auto`, conformal regions), the score tables and calibration true positives
    gathered from two worker processes give the profile the in-memory fit gives."""
    from tests.calibrators.fit.test_fit_stream import assert_close_tree

    dump = synthetic_dump(n_frames=60, n_gt_per_frame=12, seed=22)
    save_parquet(tmp_path / "ds", dump, rows_per_part=150)
    loaded = load_parquet(tmp_path / "ds")
    with dask_client("local:2") as client:
        # and with cross-fitted radii: the second pass runs on the workers too
        for options in ({"min_group": 15}, {"min_group": 15, "region_calibration": "cross"}):
            in_memory = fit_profile(loaded, **options)
            streamed = fit_profile_stream(tmp_path / "ds", client=client, **options)
            assert streamed.region_method == "conformal"
            assert_close_tree(streamed.report["selection"]["score"],
                              in_memory.report["selection"]["score"], "score")
            assert np.abs(apply_profile(loaded, streamed).scores
                          - apply_profile(loaded, in_memory).scores).max() < 1e-6
            assert_close_tree(streamed.regions, in_memory.regions, "regions", rel=1e-4)
            for source, stage in in_memory.sources.items():
                assert_close_tree(streamed.sources[source]["regions"], stage["regions"],
                                  source)


def test_a_corrupt_part_read_by_a_worker_is_named(tmp_path):
    save_parquet(tmp_path / "ds", synthetic_dump(n_frames=20, seed=23), rows_per_part=200)
    part = sorted((tmp_path / "ds" / "detections").glob("*.parquet"))[1]
    part.write_bytes(part.read_bytes()[:100])
    with dask_client("local:2") as client, pytest.raises(FieldError, match=part.name):
        fit_profile_stream(tmp_path / "ds", client=client)
