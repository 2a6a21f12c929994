"""DepthScaler: per-class k recovery, closed form, fallback, transform, validation."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators.core.checks import class_codes
from calibrators.core.errors import NotFittedError
from calibrators.covariance import (
    MANTISSA_BITS,
    OCTAVES,
    DepthScaler,
    DepthTerms,
    add_depth_term,
    brent_k,
    depth_bins,
    log_bin,
    spectral,
    spectral_2x2,
)

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
    assert DepthTerms.build(r, cov, d).nll(k) == pytest.approx(direct, rel=1e-10)


def test_closed_form_2x2_matches_eigh():
    rng = np.random.default_rng(8)
    cov = random_psd(rng, 400, 2)
    cov[:5] = [np.eye(2) * 2.0, np.diag([1.0, 3.0]), np.diag([3.0, 1.0]), np.zeros((2, 2)),
               [[1.0, 1.0], [1.0, 1.0]]]  # isotropic, diagonal both ways, zero, rank 1
    r = rng.normal(size=(400, 2))
    eig2, sq2 = spectral_2x2(cov, r)
    eig, sq = spectral(cov, r)
    np.testing.assert_allclose(eig2, eig, atol=1e-12)
    distinct = np.ones(400, dtype=bool)
    distinct[[0, 3]] = False  # equal eigenvalues: any split of |r|² is right
    np.testing.assert_allclose(sq2[:, distinct], sq[:, distinct], atol=1e-9)
    np.testing.assert_allclose(sq2.sum(axis=0), (r * r).sum(axis=1))
    d = rng.uniform(1.0, 60.0, 400)
    for k in (1e-4, 0.05, 3.0):
        assert DepthTerms(eig2, sq2, d).nll(k) == pytest.approx(DepthTerms(eig, sq, d).nll(k),
                                                                rel=1e-12)


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


# -- the binned Brent search equals the exact minimiser -----------------------------------------
def exact_k(terms: DepthTerms, members: np.ndarray, bounds=(0.0, 25.0)) -> float:
    """k minimising the exact `DepthTerms.nll` of `members` (Brent to 1e-11 on log k, then
    k = 0)."""
    sub = DepthTerms(terms.eig[:, members], terms.sq[:, members], terms.dist[members])
    k, nll = brent_k(sub, bounds[0], bounds[1], 1e-11)
    return bounds[0] if sub.nll(bounds[0]) <= nll else k


def wide_draw(dim: int, seed: int):
    """Residuals of 3 classes whose Σ span 8 decades, with singular Σ and d = 0 rows mixed in."""
    rng = np.random.default_rng(seed)
    k_true = {"car": 0.02, "pedestrian": 0.15, "barrier": 1.0}
    classes = np.repeat(np.array(list(k_true)), 4000)
    n = len(classes)
    cov = random_psd(rng, n, dim) * 10.0 ** rng.uniform(-6, 2, n)[:, None, None]
    d = rng.uniform(0.5, 80.0, n)
    d[::97] = 0.0
    cov[::97] += np.eye(dim)  # regular where d = 0
    full = add_depth_term(cov, d, np.array([k_true[c] for c in classes]))
    r = np.einsum("nij,nj->ni", np.linalg.cholesky(full + 1e-12 * np.eye(dim)),
                  rng.normal(size=(n, dim)))
    return r, cov, d, classes


@pytest.mark.parametrize("dim, seed", [(2, 0), (2, 1), (3, 2)])
def test_binned_fit_equals_the_exact_minimiser(dim, seed):
    r, cov, d, classes = wide_draw(dim, seed)
    scaler = DepthScaler().fit(r, cov, d, classes)
    terms = DepthTerms.build(r, cov, d)
    for name in scaler.k_:
        members = np.flatnonzero(classes == name)
        assert scaler.k_[name] == pytest.approx(exact_k(terms, members), rel=1e-6), name
        sub = DepthTerms(terms.eig[:, members], terms.sq[:, members], terms.dist[members])
        assert scaler.nll_[name] == pytest.approx(sub.nll(scaler.k_[name]), rel=1e-12)
    assert scaler.pooled_k_ == pytest.approx(exact_k(terms, np.arange(len(r))), rel=1e-6)
    assert scaler.pooled_nll_ == pytest.approx(terms.nll(scaler.pooled_k_), rel=1e-12)


def test_binned_nll_is_close_to_the_exact_nll():
    r, cov, d, classes = wide_draw(2, 3)
    cov[(np.arange(len(r)) % 5 == 1) & (d > 0)] = 0.0  # a = 0 pairs are summed exactly
    terms = DepthTerms.build(r, cov, d)
    keys, codes = class_codes(classes, len(classes))
    groups, pooled = depth_bins(terms, codes, len(keys))
    assert sum(g.n for g in groups) == pooled.n == len(r)
    for k in (1e-4, 0.03, 0.5, 7.0):
        assert pooled.nll(k) == pytest.approx(terms.nll(k), rel=1e-7)
        exact = terms.group_nll(np.full(len(keys), k), codes)
        for g, stats in enumerate(groups):
            assert stats.nll(k) == pytest.approx(exact[g], rel=1e-7)
    assert pooled.nll(0.0) == np.inf == terms.nll(0.0)  # Σ = 0 rows: singular at k = 0


def test_without_covariance_the_binned_search_is_exact():
    rng = np.random.default_rng(9)
    d = rng.uniform(0.0, 60.0, 3000)
    d[0] = 1.0
    r = rng.normal(size=(3000, 3)) * np.sqrt(0.2 * d)[:, None]
    scaler = DepthScaler().fit(r, None, d, np.zeros(3000, dtype=int))
    closed = float(np.sum(r**2 / d[:, None]) / r.size)
    assert scaler.k_[0] == pytest.approx(closed, rel=1e-7)


def test_log_bins_are_monotone_and_fine():
    a = np.sort(np.random.default_rng(1).uniform(0.0, 1.0, 5000) ** 8)
    a[:3] = 0.0
    key, n_bins = log_bin(a)
    assert (key[:3] == 0).all() and (key[3:] >= 1).all() and (np.diff(key) >= 0).all()
    assert key.max() == n_bins == OCTAVES << MANTISSA_BITS  # a spans more than 64 octaves
    for b in np.unique(key[key > 1]):
        inside = a[key == b]
        assert inside.max() / inside.min() - 1 <= 2.0**-MANTISSA_BITS
    assert a[key == 1].max() <= a.max() * 2.0**-(OCTAVES - 1)  # the floor bin: negligible a
    narrow, n_bins = log_bin(np.array([[1.0, 1.5], [0.0, 1.999]]))
    per_octave = 1 << MANTISSA_BITS  # 1.0 is the lowest bin; 1.5 and 1.999 the same octave
    top = int(0.999 * per_octave) + 1
    assert n_bins == top and narrow.tolist() == [[1, per_octave // 2 + 1], [0, top]]
    assert log_bin(np.zeros((2, 0)))[0].shape == (2, 0)
    assert log_bin(np.zeros(3))[0].tolist() == [0, 0, 0]


@pytest.mark.parametrize("classes", [
    np.array([3, -2, 3, 7, -2]), np.array([5, 10**12, 5]), np.array(["b", "a", "b"]),
    np.array([2, 2, 2], dtype=np.uint8)])
def test_class_codes_match_unique(classes):
    keys, codes = class_codes(classes, len(classes))
    want_keys, want_codes = np.unique(classes, return_inverse=True)
    assert keys == want_keys.tolist()
    np.testing.assert_array_equal(codes, want_codes)
    assert all(type(k) in (int, str) for k in keys)
