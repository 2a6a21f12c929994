"""FitOptions: one validated set of fit options; fit_profile takes it (or keyword overrides)."""

from __future__ import annotations

import math

import pytest

from calibrators import FitOptions, OptionError, fit_profile


def test_defaults_round_trip_and_describe():
    opts = FitOptions()
    assert opts.dims == ("x", "y") and opts.cov_source == "auto" and opts.min_score is None
    assert FitOptions.from_dict(opts.to_dict()) == opts
    assert opts.to_dict()["dims"] == ["x", "y"]
    specs = {spec.name: spec for spec in FitOptions.describe()}
    assert list(specs) == list(opts.to_dict())
    assert specs["dims"].default == "x,y" and specs["cov_source"].choices[0] == "auto"
    assert specs["min_score"].nullable and not specs["threshold"].nullable
    assert FitOptions(dims="x, y,yaw").dims == ("x", "y", "yaw")


@pytest.mark.parametrize("kwargs, field", [
    ({"threshold": 0}, "threshold"), ({"threshold": math.inf}, "threshold"),
    ({"threshold": "2"}, "threshold"), ({"dims": ""}, "dims"), ({"dims": "x,q"}, "dims"),
    ({"dims": ["x", "x"]}, "dims"), ({"cov_source": "spread"}, "cov_source"),
    ({"holdout": 1.0}, "holdout"), ({"holdout": -0.1}, "holdout"),
    ({"min_score": 1.5}, "min_score"), ({"min_score": math.nan}, "min_score"),
    ({"min_samples": 0}, "min_samples"), ({"min_samples": 2.5}, "min_samples"),
    ({"min_samples": True}, "min_samples"), ({"seed": -1}, "seed"),
    ({"seed": math.inf}, "seed"), ({"modulation": "yes"}, "modulation"),
])
def test_bad_values_name_the_option(kwargs, field):
    with pytest.raises(OptionError, match=field) as info:
        FitOptions(**kwargs)
    assert info.value.field == field
    assert isinstance(info.value, ValueError)


def test_unknown_key_is_refused():
    with pytest.raises(OptionError, match="unknown fit option 'tresh'") as info:
        FitOptions.from_dict({"tresh": 1.0})
    assert info.value.field == "tresh"


def test_fit_profile_takes_options_or_overrides(small_dump):
    a = fit_profile(small_dump, FitOptions(holdout=0.25, cov_source="layers"))
    b = fit_profile(small_dump, holdout=0.25, cov_source="layers")
    c = fit_profile(small_dump, FitOptions(holdout=0.25), cov_source="layers")
    for other in (b, c):
        assert other.temperature == a.temperature and other.depth_k == a.depth_k
    with pytest.raises(OptionError, match="options must be a FitOptions"):
        fit_profile(small_dump, {"holdout": 0.25})
