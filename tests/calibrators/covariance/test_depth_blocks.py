"""Depth scaling in cache-sized blocks: the same numbers as one pass over all samples."""

from __future__ import annotations

import numpy as np
import pytest

# The block sizes patched below (`_CHUNK`, `_BLOCK`) are globals of these private modules, read
# at call time: the modules are imported for that alone (allowed in tests/test_imports.py).
import calibrators.covariance._depth_nll as depth_nll
import calibrators.covariance._spectral as _spectral
from calibrators.covariance import BinSums, DepthTerms, log_bin_low, spectral_2x2


def psd_2x2(rng: np.random.Generator, n: int, huge: bool = True) -> np.ndarray:
    """`[n, 2, 2]` PSD matrices: random, rank 1 every 7th, zero every 11th, and (`huge`) the
    13th of the first half times 1e160 (so that h is taken by hypot in every block)."""
    a = rng.normal(0.0, 0.7, size=(n, 2, 2))
    a[::7, :, 0] = 0.0
    cov = a @ np.swapaxes(a, 1, 2)
    cov[::11] = 0.0
    if huge:
        cov[:n // 2:13] *= 1e160
    return cov


def one_pass_sums(terms: DepthTerms, codes: np.ndarray, n_groups: int) -> tuple:
    """`BinSums.build` as one `np.bincount` over all `[D, N]` pairs: `(n, const, low, sums)`."""
    near = terms.dist == 0
    with np.errstate(divide="ignore"):
        row_const = terms.eig.shape[0] * np.log(terms.dist)
    eig, sq = terms.eig[:, near], terms.sq[:, near]
    row_const[near] = (np.log(eig) + sq / eig).sum(axis=0)
    const = np.bincount(codes, weights=row_const, minlength=n_groups)
    far = ~near
    a, b = terms.eig[:, far] / terms.dist[far], terms.sq[:, far] / terms.dist[far]
    key, n_bins, low = log_bin_low(a)
    key = (key + codes[far] * (n_bins + 1)).ravel()
    size = n_groups * (n_bins + 1)
    sums = np.stack([np.bincount(key, weights=w, minlength=size).reshape(n_groups, -1)
                     for w in (None, a.ravel(), b.ravel(), (a * b).ravel())])
    return np.bincount(codes, minlength=n_groups), const, low, sums


def test_blocks_of_the_closed_form_2x2_equal_one_block(monkeypatch):
    rng = np.random.default_rng(0)
    cov, r = psd_2x2(rng, 200), rng.normal(size=(200, 2))
    r[::13] *= 1e70
    whole = spectral_2x2(cov, r)
    monkeypatch.setattr(_spectral, "_BLOCK", 7)
    blocks = spectral_2x2(cov, r)
    for x, y in zip(whole, blocks, strict=True):
        np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize(("psd_row", "asym_row", "match"), [
    (2, 16, r"covariances\[16\] is not symmetric"),          # asymmetry first, in any block
    (12, None, r"covariances\[12\] is not positive semi-definite"),
    (None, 6, r"covariances\[6\] is not symmetric"),
])
def test_blocks_name_the_row_one_block_would(monkeypatch, psd_row, asym_row, match):
    rng = np.random.default_rng(1)
    cov, r = psd_2x2(rng, 20), rng.normal(size=(20, 2))
    if psd_row is not None:
        cov[psd_row] = [[1.0, 2.0], [2.0, 1.0]]
    if asym_row is not None:
        cov[asym_row, 0, 1] += 0.5
    monkeypatch.setattr(_spectral, "_BLOCK", 5)
    with pytest.raises(ValueError, match=match):
        spectral_2x2(cov, r)


@pytest.mark.parametrize("near", [True, False])
@pytest.mark.parametrize("kind", ["plain", "zeros", "wide"])
def test_bin_sums_in_blocks_equal_one_bincount(monkeypatch, kind, near):
    """Bit for bit, with (`near`) d = 0 rows inside blocks, else with the grid taken while
    decomposing; `plain`: every a > 0 within the grid, `zeros`: some a = 0, `wide`: a over
    more than `OCTAVES` octaves (the grid's floor)."""
    rng = np.random.default_rng(2)
    n = 500
    a = rng.normal(0.0, 0.7, size=(n, 2, 2))
    cov = {"plain": a @ np.swapaxes(a, 1, 2), "zeros": psd_2x2(rng, n, huge=False),
           "wide": psd_2x2(rng, n)}[kind]
    r, d = rng.normal(size=(n, 2)), rng.uniform(1.0, 60.0, size=n)
    if near:
        d[5::37] = 0.0
        cov[5::37] = [[1.0, 0.2], [0.2, 3.0]]  # Σ regular where d = 0
    codes = rng.integers(0, 3, size=n)
    monkeypatch.setattr(depth_nll, "_CHUNK", 16)
    monkeypatch.setattr(_spectral, "_BLOCK", 9)
    terms = DepthTerms.build(r, cov, d)
    assert (terms.grid is None) == near
    got = BinSums.build(terms, codes, 3)
    n_ref, const, low, sums = one_pass_sums(terms, codes, 3)
    np.testing.assert_array_equal(got.n, n_ref)
    np.testing.assert_array_equal(got.const, const)
    assert got.low == low
    np.testing.assert_array_equal(got.sums, sums)


def test_bin_sums_without_any_positive_a():
    r, d = np.ones((4, 2)), np.array([1.0, 2.0, 3.0, 4.0])
    got = BinSums.build(DepthTerms.build(r, None, d), np.array([0, 1, 1, 0]), 2)
    n_ref, const, low, sums = one_pass_sums(DepthTerms.build(r, None, d), np.array([0, 1, 1, 0]), 2)
    assert got.low == low == 0 and got.sums.shape == sums.shape == (4, 2, 1)
    np.testing.assert_array_equal(got.sums, sums)
    np.testing.assert_array_equal(got.const, const)


def test_fitted_nll_equals_group_and_pooled_nll(monkeypatch):
    rng = np.random.default_rng(3)
    cov, r = psd_2x2(rng, 300) * 1e-3, rng.normal(size=(300, 2))
    terms = DepthTerms.build(r, cov, rng.uniform(1.0, 60.0, size=300))
    codes, k = rng.integers(0, 4, size=300), np.array([0.0, 0.01, 0.1, 1.0])
    monkeypatch.setattr(depth_nll, "_CHUNK", 32)
    group, pooled = terms.fitted_nll(k, codes, 0.05)
    np.testing.assert_array_equal(group, terms.group_nll(k, codes))
    assert pooled == terms.nll(0.05)
    group_n, _ = terms.fitted_nll(k, codes, 0.05, np.bincount(codes, minlength=4))
    np.testing.assert_array_equal(group_n, group)
