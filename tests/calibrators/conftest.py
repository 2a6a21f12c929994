"""Shared synthetic dumps and profiles for the fit and report tests (built once per session)."""

from __future__ import annotations

import pytest

from calibrators.data import synthetic_dump

# Large enough that T (within 10 %) and the k of common classes are stable across seeds,
# small enough that a fit takes well under a second.
N_FRAMES = 150


@pytest.fixture(scope="session")
def sigmoid_dump():
    return synthetic_dump(n_frames=N_FRAMES, temperature=2.0, seed=3)


@pytest.fixture(scope="session")
def softmax_dump():
    return synthetic_dump(n_frames=N_FRAMES, score_mode="softmax", temperature=1.5, seed=4)


@pytest.fixture(scope="session")
def small_dump():
    return synthetic_dump(n_frames=20, seed=5)


@pytest.fixture(scope="session")
def sigmoid_profile(sigmoid_dump):
    from calibrators.fit import fit_profile

    return fit_profile(sigmoid_dump, cov_source="given", holdout=0.3, seed=1)
