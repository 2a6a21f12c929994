"""ShrinkageDepthScaler: (s_c, k_c) recovery, the s = 1 case is DepthScaler, exact optimum,
fallback, transform, round trip and validation."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibrators.core.errors import NotFittedError
from calibrators.covariance import DepthScaler, ShrinkageDepthScaler, add_depth_term
from calibrators.metrics import regression_nll

TRUTH = {"car": (0.5, 0.02), "pedestrian": (2.0, 0.01), "barrier": (1.0, 0.05)}


def draw(truth: dict, n_per_class: int, dim: int = 2, seed: int = 0, n_near: int = 0):
    """Residuals ~ N(0, s_c·Σ + k_c·d·I), Σ random SPD with eigenvalues O(1) independent of
    d ~ U(1, 60) m (so s and k are identifiable); the first `n_near` rows sit at d = 0."""
    rng = np.random.default_rng(seed)
    classes = rng.permutation(np.repeat(np.array(list(truth)), n_per_class))
    n = classes.size
    d = rng.uniform(1.0, 60.0, n)
    d[:n_near] = 0.0
    a = rng.normal(0.0, 0.7, (n, dim, dim))
    cov = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(dim)
    s = np.array([truth[c][0] for c in classes])
    k = np.array([truth[c][1] for c in classes])
    full = add_depth_term(cov * s[:, None, None], d, k)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(full), rng.normal(size=(n, dim)))
    return r, cov, d, classes


@pytest.mark.parametrize("dim", [2, 3])
def test_recovers_s_and_k_per_class(dim):
    r, cov, d, classes = draw(TRUTH, 20000, dim=dim, seed=dim)
    scaler = ShrinkageDepthScaler().fit(r, cov, d, classes)
    for name, (s, k) in TRUTH.items():
        assert scaler.s_[name] == pytest.approx(s, rel=0.06), name
        assert scaler.k_[name] == pytest.approx(k, rel=0.06), name
    assert scaler.fallback_classes_ == [] and scaler.n_dims_ == dim


def test_fixed_unit_scale_is_depth_scaling():
    r, cov, d, classes = draw(TRUTH, 1500, seed=4, n_near=30)
    fixed = ShrinkageDepthScaler(scale_bounds=(1.0, 1.0)).fit(r, cov, d, classes)
    depth = DepthScaler().fit(r, cov, d, classes)
    assert set(fixed.s_.values()) == {1.0} and fixed.pooled_s_ == 1.0
    for name in TRUTH:
        assert fixed.k_[name] == pytest.approx(depth.k_[name], rel=1e-6, abs=1e-12)
        assert fixed.nll_[name] == pytest.approx(depth.nll_[name], rel=1e-9)
    assert fixed.pooled_k_ == pytest.approx(depth.pooled_k_, rel=1e-6)


def test_without_covariance_s_is_one_and_k_is_depth_scaling():
    r, _, d, classes = draw(TRUTH, 1000, seed=5)
    shrink = ShrinkageDepthScaler().fit(r, None, d, classes)
    depth = DepthScaler().fit(r, None, d, classes)
    assert set(shrink.s_.values()) == {1.0}
    for name in TRUTH:
        assert shrink.k_[name] == pytest.approx(depth.k_[name], rel=1e-6)


def test_fitted_pair_minimises_the_exact_nll():
    """Including rows at d = 0, whose k-free terms depend on s."""
    r, cov, d, classes = draw({"car": (0.7, 0.03)}, 3000, seed=6, n_near=300)
    scaler = ShrinkageDepthScaler().fit(r, cov, d, classes)
    s, k = scaler.s_["car"], scaler.k_["car"]

    def nll(s_: float, k_: float) -> float:
        return regression_nll(r, add_depth_term(s_ * cov, d, np.full(d.size, k_)))

    best = nll(s, k)
    assert best == pytest.approx(scaler.nll_["car"], rel=1e-12)
    for ds, dk in [(1.002, 1.0), (0.998, 1.0), (1.0, 1.002), (1.0, 0.998), (1.002, 0.998)]:
        assert best < nll(s * ds, k * dk)


def test_small_class_takes_the_pooled_pair_and_unseen_class_too():
    r, cov, d, classes = draw(TRUTH, 1000, seed=7)
    classes = classes.astype(object)
    classes[:20] = "bus"
    scaler = ShrinkageDepthScaler(min_samples=50).fit(r, cov, d, classes)
    assert scaler.fallback_classes_ == ["bus"] and scaler.nll_["bus"] is None
    assert (scaler.s_["bus"], scaler.k_["bus"]) == (scaler.pooled_s_, scaler.pooled_k_)
    out = scaler.transform(cov[:2], d[:2], np.array(["truck", "car"]))
    np.testing.assert_allclose(out[0], scaler.pooled_s_ * cov[0]
                               + scaler.pooled_k_ * d[0] * np.eye(2))
    np.testing.assert_allclose(out[1], scaler.s_["car"] * cov[1]
                               + scaler.k_["car"] * d[1] * np.eye(2))


def test_round_trip_transforms_identically():
    r, cov, d, classes = draw(TRUTH, 500, seed=8)
    scaler = ShrinkageDepthScaler().fit(r, cov, d, classes)
    back = ShrinkageDepthScaler.from_dict(json.loads(json.dumps(scaler.to_dict(),
                                                                allow_nan=False)))
    np.testing.assert_array_equal(back.transform(cov, d, classes),
                                  scaler.transform(cov, d, classes))
    assert back.to_dict() == scaler.to_dict()
    ints = ShrinkageDepthScaler().fit(r, cov, d, np.unique(classes, return_inverse=True)[1])
    assert list(ShrinkageDepthScaler.from_dict(ints.to_dict()).k_) == [0, 1, 2]


def test_validation_names_the_argument():
    r, cov, d, classes = draw(TRUTH, 100, seed=9)
    with pytest.raises(NotFittedError):
        ShrinkageDepthScaler().transform(cov, d, classes)
    with pytest.raises(ValueError, match="scale_bounds"):
        ShrinkageDepthScaler(scale_bounds=(2.0, 1.0)).fit(r, cov, d, classes)
    with pytest.raises(ValueError, match="scale_bounds"):
        ShrinkageDepthScaler(scale_bounds=(0.0, 1.0)).fit(r, cov, d, classes)
    with pytest.raises(ValueError, match="distances"):
        ShrinkageDepthScaler().fit(r, cov, -d, classes)
    with pytest.raises(ValueError, match="covariances"):
        ShrinkageDepthScaler().fit(r, cov[:, :1, :1], d, classes)
    with pytest.raises(ValueError, match="lacks 's'"):
        ShrinkageDepthScaler.from_dict({"hyper": {}, "classes": [], "k": []})
