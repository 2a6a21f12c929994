"""DepthScaler: per-class k recovery, closed form, fallback, transform, validation."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.depth import DepthScaler, _spectral, _spectral_2x2, _Terms, add_depth_term
from calibrators.exceptions import NotFittedError

K_TRUE = {"car": 0.02, "pedestrian": 0.08, "barrier": 0.3}


def random_psd(rng: np.random.Generator, n: int, dim: int, scale: float = 0.5) -> np.ndarray:
    """`[n, dim, dim]` random PSD matrices A Aᵀ, with rank-deficient ones mixed in."""
    a = rng.normal(0.0, np.sqrt(scale), size=(n, dim, dim))
    a[::7, :, 0] = 0.0  # every 7th has rank dim - 1
    return a @ np.swapaxes(a, 1, 2)


def draw(k_true: dict, n_per_class: int, dim: int = 2, seed: int = 0, with_cov: bool = True):
    """Residuals ~ N(0, Σ + k_c d I), distances U(1, 60) m, classes as names."""
    rng = np.random.default_rng(seed)
    classes = np.repeat(np.array(list(k_true)), n_per_class)
    n = len(classes)
    d = rng.uniform(1.0, 60.0, size=n)
    cov = random_psd(rng, n, dim) if with_cov else None
    k = np.array([k_true[c] for c in classes])
    full = add_depth_term(np.zeros((n, dim, dim)) if cov is None else cov, d, k)
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(full), rng.normal(size=(n, dim)))
    perm = rng.permutation(n)  # interleave classes
    return r[perm], (None if cov is None else cov[perm]), d[perm], classes[perm]


@pytest.mark.parametrize("dim", [2, 3])
def test_recovers_per_class_k_within_5_percent(dim):
    r, cov, d, classes = draw(K_TRUE, 8000, dim=dim, seed=dim)
    scaler = DepthScaler().fit(r, cov, d, classes)
    assert set(scaler.k_) == set(K_TRUE)
    for name, k in K_TRUE.items():
        assert scaler.k_[name] == pytest.approx(k, rel=0.05), name
    assert scaler.fallback_classes_ == []
    assert scaler.n_samples_ == {name: 8000 for name in K_TRUE}
    assert scaler.n_dims_ == dim
    assert all(isinstance(key, str) for key in scaler.k_)


def test_without_covariance_matches_closed_form():
    # With Σ = 0, dNLL/dk = 0 gives k = Σ_i |r_i|² / d_i / (N D).
    rng = np.random.default_rng(5)
    d = rng.uniform(1.0, 60.0, 4000)
    r = rng.normal(size=(4000, 2)) * np.sqrt(0.1 * d)[:, None]
    scaler = DepthScaler().fit(r, None, d, np.zeros(4000, dtype=int))
    closed = float(np.sum(r**2 / d[:, None]) / r.size)
    assert scaler.k_[0] == pytest.approx(closed, rel=1e-6)
    assert scaler.pooled_k_ == pytest.approx(closed, rel=1e-6)


def test_nll_terms_match_the_direct_gaussian_nll():
    rng = np.random.default_rng(2)
    cov = random_psd(rng, 50, 3)
    r = rng.normal(size=(50, 3))
    d = rng.uniform(1.0, 60.0, 50)
    k = 0.37
    full = add_depth_term(cov, d, np.full(50, k))
    _, logdet = np.linalg.slogdet(full)
    maha = np.einsum("ni,ni->n", r, np.linalg.solve(full, r[..., None])[..., 0])
    direct = np.mean(0.5 * (logdet + maha + 3 * np.log(2 * np.pi)))
    assert _Terms.build(r, cov, d).nll(k) == pytest.approx(direct, rel=1e-10)


def test_closed_form_2x2_matches_eigh():
    rng = np.random.default_rng(8)
    cov = random_psd(rng, 400, 2)
    cov[:5] = [np.eye(2) * 2.0, np.diag([1.0, 3.0]), np.diag([3.0, 1.0]), np.zeros((2, 2)),
               [[1.0, 1.0], [1.0, 1.0]]]  # isotropic, diagonal both ways, zero, rank 1
    r = rng.normal(size=(400, 2))
    eig2, sq2 = _spectral_2x2(cov, r)
    eig, sq = _spectral(cov, r)
    np.testing.assert_allclose(eig2, eig, atol=1e-12)
    distinct = np.ones(400, dtype=bool)
    distinct[[0, 3]] = False  # equal eigenvalues: any split of |r|² is right
    np.testing.assert_allclose(sq2[:, distinct], sq[:, distinct], atol=1e-9)
    np.testing.assert_allclose(sq2.sum(axis=0), (r * r).sum(axis=1))
    d = rng.uniform(1.0, 60.0, 400)
    for k in (1e-4, 0.05, 3.0):
        assert _Terms(eig2, sq2, d).nll(k) == pytest.approx(_Terms(eig, sq, d).nll(k), rel=1e-12)


def test_small_classes_fall_back_to_pooled_k():
    r, cov, d, classes = draw({"car": 0.05, "bus": 0.05, "bicycle": 0.5}, 3000, seed=1)
    keep = (classes != "bicycle") | (np.cumsum(classes == "bicycle") <= 20)
    scaler = DepthScaler(min_samples=50).fit(r[keep], cov[keep], d[keep], classes[keep])
    assert scaler.fallback_classes_ == ["bicycle"]
    assert scaler.n_samples_["bicycle"] == 20
    assert scaler.k_["bicycle"] == scaler.pooled_k_
    assert scaler.k_["car"] == pytest.approx(0.05, rel=0.1)
    assert scaler.pooled_k_ == pytest.approx(0.05, rel=0.1)  # 6000 cars and buses dominate


def test_transform_shapes_and_unseen_class_uses_pooled_k():
    r, cov, d, classes = draw({0: 0.05, 1: 0.2}, 2000, seed=3)
    scaler = DepthScaler().fit(r, cov, d, classes)
    out = scaler.transform(cov[:4], np.array([0.0, 10.0, 10.0, 10.0]), np.array([0, 0, 1, 7]))
    assert out.shape == (4, 2, 2)
    added = np.einsum("nii->ni", out - cov[:4])
    np.testing.assert_allclose(added[0], 0.0)
    np.testing.assert_allclose(added[1], 10 * scaler.k_[0])
    np.testing.assert_allclose(added[2], 10 * scaler.k_[1])
    np.testing.assert_allclose(added[3], 10 * scaler.pooled_k_)
    np.testing.assert_allclose(out - np.swapaxes(out, 1, 2), 0.0)
    no_cov = scaler.transform(None, np.array([2.0]), np.array([1]))
    np.testing.assert_allclose(no_cov, 2 * scaler.k_[1] * np.eye(2)[None])
    assert scaler.transform(None, np.zeros(0), np.zeros(0, dtype=int)).shape == (0, 2, 2)


def test_k_is_zero_when_covariance_already_too_wide():
    rng = np.random.default_rng(4)
    cov = np.tile(np.eye(2) * 4.0, (500, 1, 1))
    r = rng.normal(size=(500, 2)) * 0.5  # true variance 0.25 << 4
    scaler = DepthScaler().fit(r, cov, rng.uniform(1, 60, 500), np.zeros(500, dtype=int))
    assert scaler.k_[0] == 0.0


def test_optimum_beyond_the_upper_bound_is_found_by_widening_once():
    r, cov, d, classes = draw({"far": 40.0}, 2000, seed=6, with_cov=False)
    scaler = DepthScaler(bounds=(0.0, 5.0)).fit(r, cov, d, classes)
    assert scaler.k_["far"] == pytest.approx(40.0, rel=0.1)


def test_transform_before_fit_raises_not_fitted():
    with pytest.raises(NotFittedError, match="DepthScaler is not fitted"):
        DepthScaler().transform(None, np.ones(2), np.zeros(2))


def _good(n: int = 60):
    rng = np.random.default_rng(0)
    return rng.normal(size=(n, 2)), random_psd(rng, n, 2) + np.eye(2), \
        rng.uniform(1, 60, n), np.zeros(n, dtype=int)


@pytest.mark.parametrize("which, value, match", [
    (0, "nan", r"residuals has NaN at index \[3, 1\]"),
    (0, "empty", "residuals is empty"),
    (0, "1d", "residuals must have 2 dimensions"),
    (1, "nan", r"covariances has NaN"),
    (1, "nonpsd", r"covariances\[3\] is not positive semi-definite"),
    (1, "asym", r"covariances\[3\] is not symmetric"),
    (1, "short", "covariances has 59 matrices but 60 were expected"),
    (1, "3x3", "covariances must be 2x2"),
    (2, "negative", r"distances\[3\] = -1.0 is negative"),
    (2, "short", "distances has 59 rows but residuals has 60"),
    (2, "nan", r"distances has NaN at index 3"),
    (3, "short", "classes has 59 rows but distances has 60"),
    (3, "2d", "classes must have 1 dimension"),
    (3, "mixed", "classes must be labels of one comparable type"),
])
def test_bad_input_names_the_argument(which, value, match):
    args = list(_good())
    arr = args[which]
    if value == "nan":
        arr = arr.astype(float)
        arr[(3, 1) if arr.ndim == 2 else (3,) if arr.ndim == 1 else (3, 0, 0)] = np.nan
    elif value == "empty":
        arr = arr[:0]
    elif value == "1d":
        arr = arr[:, 0]
    elif value == "nonpsd":
        arr = arr.copy()
        arr[3] = [[1.0, 2.0], [2.0, 1.0]]
    elif value == "asym":
        arr = arr.copy()
        arr[3, 0, 1] += 0.5
    elif value == "short":
        arr = arr[:-1]
    elif value == "3x3":
        arr = np.tile(np.eye(3), (60, 1, 1))
    elif value == "negative":
        arr = arr.copy()
        arr[3] = -1.0
    elif value == "2d":
        arr = arr[:, None]
    elif value == "mixed":
        arr = np.array([0, "a"] * 30, dtype=object)
    args[which] = arr
    with pytest.raises(ValueError, match=match):
        DepthScaler().fit(*args)


def test_zero_distance_with_singular_covariance_is_refused():
    r, cov, d, classes = _good()
    cov[5] = [[1.0, 1.0], [1.0, 1.0]]  # rank 1
    d[5] = 0.0
    with pytest.raises(ValueError, match=r"distances\[5\] is 0 and covariances\[5\] is singular"):
        DepthScaler().fit(r, cov, d, classes)
    with pytest.raises(ValueError, match=r"distances\[5\] is 0 and covariances is None"):
        DepthScaler().fit(r, None, d, classes)
    cov[5] = np.eye(2)  # regular Σ at d = 0 is fine
    DepthScaler().fit(r, cov, d, classes)


@pytest.mark.parametrize("kwargs, match", [
    ({"min_samples": 0}, "min_samples must be an integer >= 1"),
    ({"min_samples": 2.5}, "min_samples must be an integer"),
    ({"bounds": (-1.0, 5.0)}, "bounds must satisfy 0 <= low < high"),
    ({"bounds": (0.0, np.inf)}, "bounds must satisfy"),
])
def test_bad_hyper_parameters(kwargs, match):
    with pytest.raises(ValueError, match=match):
        DepthScaler(**kwargs).fit(*_good())
