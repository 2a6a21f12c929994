"""Every estimator follows one convention (docs/architecture.md): `fit(...)` returns self, what
fit sets ends in `_` and is absent before (serving raises NotFittedError), `to_dict()` is strict
JSON, and `from_dict(to_dict())` serves bit for bit what the fitted estimator serves."""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest

from calibrators.boxes2d import ConformalBoxes, PositionCalibrator
from calibrators.core.errors import NotFittedError
from calibrators.covariance import DepthScaler, ShrinkageDepthScaler
from calibrators.regions import ConformalRegions
from calibrators.scores import (
    ClassTemperatureScaler,
    HistogramBinning,
    IsotonicCalibrator,
    PlattScaler,
    TemperatureScaler,
)

RNG_SEED = 7


@dataclass(frozen=True)
class Case:
    """An unfitted estimator, the arguments of its `fit`, and how it serves (`transform`)."""

    make: Callable[[], Any]
    fit_args: tuple
    serve: Callable[[Any], np.ndarray]


def _score_case(make: Callable[[], Any]) -> Case:
    rng = np.random.default_rng(RNG_SEED)
    n, c = 900, 4
    labels = rng.integers(0, c, n)
    labels[:12] = 3                     # class 3 is rare: it takes the pooled fit
    labels[12:][labels[12:] == 3] = 0
    z = rng.normal(0.0, 2.0, n)
    dist = rng.uniform(0.0, 60.0, n)
    tp = rng.random(n) < 1.0 / (1.0 + np.exp(-(0.7 * z - 0.02 * dist)))
    args = (z, labels, tp, c, dist)
    return Case(make, args, lambda est: est.transform(z, labels, distances=dist))


def _temperature_case(mode: str) -> Case:
    rng = np.random.default_rng(RNG_SEED)
    n, c = 2000, 3
    logits = rng.normal(0.0, 2.0, (n, c + (mode == "softmax")))
    if mode == "sigmoid":
        labels = (rng.random(n) < 1.0 / (1.0 + np.exp(-0.5 * logits.max(axis=1)))).astype(int)
    else:
        labels = rng.integers(0, c + 1, n)
    return Case(lambda: TemperatureScaler(mode=mode), (logits, labels),
                lambda est: est.transform(logits))


def _depth_case(make: Callable[[], Any], classes_of: Callable[[np.ndarray], np.ndarray],
                with_sigma: bool = True) -> Case:
    rng = np.random.default_rng(RNG_SEED)
    n = 600
    codes = np.where(np.arange(n) < 20, 2, rng.integers(0, 2, n))   # class 2: pooled
    classes = classes_of(codes)
    dist = rng.uniform(0.0, 50.0, n)
    dist[:5] = 0.0 if with_sigma else 1e-3   # d = 0 needs a regular Σ
    a = rng.normal(size=(n, 2, 2))
    cov = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(2)
    scale = (1.5 * cov + (0.05 * dist)[:, None, None] * np.eye(2))
    res = np.einsum("nij,nj->ni", np.linalg.cholesky(scale), rng.normal(size=(n, 2)))
    if not with_sigma:                  # Σ = None: Σ' = k·d·I; a class unseen at fit is served
        unseen = np.r_[classes[:4], 9]
        return Case(make, (res, None, dist, classes),
                    lambda est: est.transform(None, dist[:5], unseen))
    return Case(make, (res, cov, dist, classes),
                lambda est: est.transform(cov, dist, classes))


def _conformal_case() -> Case:
    rng = np.random.default_rng(RNG_SEED)
    n = 1500
    classes = rng.integers(0, 3, n)
    classes[:40] = 3                    # a small class: pooled with the others' bins
    classes[40:][classes[40:] == 3] = 0
    dist = rng.uniform(0.0, 80.0, n)
    scores = np.sqrt(rng.chisquare(2, n)) * (1.0 + dist / 100.0)
    levels = (0.5, 0.9, 0.99, 0.999)
    return Case(lambda: ConformalRegions(min_group=60), (scores, classes, dist),
                lambda est: est.radii(levels, np.r_[classes, 7], np.r_[dist, 200.0]))


def _position_case() -> Case:
    rng = np.random.default_rng(RNG_SEED)
    n, c = 900, 3
    labels = np.where(np.arange(n) < 10, 2, rng.integers(0, 2, n))   # class 2: pooled
    z = rng.normal(0.0, 2.0, n)
    feats = rng.random((n, 4))
    tp = rng.random(n) < 1.0 / (1.0 + np.exp(-(0.8 * z + feats[:, 0] - feats[:, 3])))
    return Case(PositionCalibrator, (z, labels, tp, c, feats),
                lambda est: est.transform(z, labels, feats))


def _box_regions_case(score: str) -> Case:
    rng = np.random.default_rng(RNG_SEED)
    n = 1200
    xy, wh = rng.uniform(0, 500, (n, 2)), rng.uniform(4, 200, (n, 2))
    boxes = np.column_stack([xy, wh])
    sigma = 0.05 * np.repeat(wh, 2, axis=1) + 0.5
    true = boxes + rng.normal(size=(n, 4)) * sigma * [1, 1, 0.5, 0.5]
    true[:, 2:] = np.abs(true[:, 2:])
    labels = np.where(np.arange(n) < 30, 2, rng.integers(0, 2, n))   # class 2: pooled
    levels = (0.5, 0.9, 0.99)
    return Case(lambda: ConformalBoxes(score=score, min_group=60),
                (boxes, true, labels, None if score == "additive" else sigma),
                lambda est: np.stack(est.regions(boxes[:50], labels[:50], sigma[:50], levels)))


CASES = {
    "position_2d": _position_case(),
    "box_regions_additive": _box_regions_case("additive"),
    "box_regions_scaled": _box_regions_case("scaled"),
    "temperature_sigmoid": _temperature_case("sigmoid"),
    "temperature_softmax": _temperature_case("softmax"),
    "class_temperature": _score_case(ClassTemperatureScaler),
    "platt": _score_case(PlattScaler),
    "platt_range": _score_case(lambda: PlattScaler(range_term=True)),
    "isotonic": _score_case(IsotonicCalibrator),
    "histogram": _score_case(HistogramBinning),
    "depth_int_classes": _depth_case(DepthScaler, lambda codes: codes),
    "depth_names": _depth_case(DepthScaler, lambda codes: np.array(["car", "bus", "ped"])[codes]),
    "depth_no_sigma": _depth_case(DepthScaler, lambda codes: codes, with_sigma=False),
    "shrinkage": _depth_case(ShrinkageDepthScaler,
                             lambda codes: np.array(["car", "bus", "ped"])[codes]),
    "conformal": _conformal_case(),
}


@pytest.fixture(scope="module", params=sorted(CASES))
def fitted(request: pytest.FixtureRequest) -> tuple[Case, Any, set[str]]:
    """(case, fitted estimator, the attributes fit added)."""
    case = CASES[request.param]
    est = case.make()
    before = set(vars(est))
    with warnings.catch_warnings():     # a k or s at the edge of its bounds: not the point here
        warnings.simplefilter("ignore", RuntimeWarning)
        out = est.fit(*case.fit_args)
    assert out is est, "fit must return self"
    return case, est, set(vars(est)) - before


def test_fitted_attributes_end_in_an_underscore_and_are_absent_before_fit(fitted):
    case, est, added = fitted
    assert added, "fit set no attribute"
    assert all(name.endswith("_") and not name.startswith("_") for name in added), added
    fresh = case.make()
    assert not any(hasattr(fresh, name) for name in added)
    with pytest.raises(NotFittedError):
        case.serve(fresh)
    with pytest.raises(NotFittedError):
        fresh.to_dict()


def test_to_dict_is_strict_json_and_from_dict_serves_bit_for_bit(fitted):
    case, est, added = fitted
    text = json.dumps(est.to_dict(), allow_nan=False)
    back = type(est).from_dict(json.loads(text))
    assert type(back) is type(est)
    assert {n for n in vars(back) if n.endswith("_")} == added
    served, again = case.serve(est), case.serve(back)
    assert served.dtype == again.dtype and served.shape == again.shape
    assert served.tobytes() == again.tobytes()
    assert json.dumps(back.to_dict(), allow_nan=False) == text


@pytest.mark.parametrize("name", sorted(CASES))
def test_from_dict_refuses_what_is_not_a_dict_form(name):
    est_type = type(CASES[name].make())
    with pytest.raises(ValueError, match="must be a dict"):
        est_type.from_dict([1, 2])
    with pytest.raises(ValueError, match="lacks"):
        est_type.from_dict({})
