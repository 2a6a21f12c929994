"""ellipse(): hand cases, angle range, batch vs single, coverage of Gaussian samples."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from calibrators.regions import Ellipse, chi2_2_quantile, ellipse


def rotation(theta: float) -> np.ndarray:
    return np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])


def test_quantile_matches_scipy():
    for p in (0.5, 0.95, 0.99, 0.3935):
        assert chi2_2_quantile(p) == pytest.approx(chi2(2).ppf(p), rel=1e-12)


def test_diagonal_cases():
    q = chi2(2).ppf(0.95)
    e = ellipse(np.diag([4.0, 1.0]))
    assert isinstance(e, Ellipse) and isinstance(e.semi_major, float)
    assert e.semi_major == pytest.approx(2.0 * np.sqrt(q))
    assert e.semi_minor == pytest.approx(np.sqrt(q))
    assert e.angle == 0.0
    e = ellipse(np.diag([1.0, 4.0]), confidence=0.5)
    assert e.semi_major == pytest.approx(2.0 * np.sqrt(chi2(2).ppf(0.5)))
    assert e.angle == pytest.approx(np.pi / 2)  # major along y: +pi/2, never -pi/2
    e = ellipse(np.array([[1.0, -0.0], [-0.0, 4.0]]))
    assert e.angle == pytest.approx(np.pi / 2)


@pytest.mark.parametrize("theta", [0.3, -0.3, 1.2, -1.2, np.pi / 2 - 1e-6, np.pi / 4])
def test_rotated_by_known_angle(theta):
    cov = rotation(theta) @ np.diag([9.0, 0.25]) @ rotation(theta).T
    e = ellipse(cov, confidence=0.9)
    q = chi2(2).ppf(0.9)
    assert e.semi_major == pytest.approx(3.0 * np.sqrt(q))
    assert e.semi_minor == pytest.approx(0.5 * np.sqrt(q))
    assert e.angle == pytest.approx(theta, abs=1e-9)
    # the same axis rotated by pi lands back in (-pi/2, pi/2]
    assert ellipse(rotation(theta + np.pi) @ np.diag([9.0, 0.25]) @ rotation(theta + np.pi).T
                   ).angle == pytest.approx(theta, abs=1e-9)


def test_isotropic_and_degenerate():
    e = ellipse(np.eye(2) * 2.0)
    assert e.semi_major == pytest.approx(e.semi_minor)
    assert e.angle == 0.0
    e = ellipse(np.zeros((2, 2)))
    assert (e.semi_major, e.semi_minor, e.angle) == (0.0, 0.0, 0.0)
    e = ellipse(np.array([[1.0, 1.0], [1.0, 1.0]]))  # a segment along 45 degrees
    assert e.semi_minor == pytest.approx(0.0, abs=1e-7)
    assert e.angle == pytest.approx(np.pi / 4)


def test_batch_matches_single_and_angle_range():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(500, 2, 2))
    cov = a @ np.swapaxes(a, 1, 2)
    batch = ellipse(cov)
    assert all(isinstance(x, np.ndarray) and x.shape == (500,) for x in batch)
    assert np.all(batch.angle > -np.pi / 2) and np.all(batch.angle <= np.pi / 2)
    assert np.all(batch.semi_major >= batch.semi_minor)
    for i in (0, 17, 499):
        single = ellipse(cov[i])
        np.testing.assert_allclose(single, [x[i] for x in batch])
    # semi-axes agree with an eigendecomposition
    eig = np.linalg.eigvalsh(cov)
    np.testing.assert_allclose(batch.semi_major, np.sqrt(eig[:, 1] * chi2(2).ppf(0.95)))
    assert ellipse(np.zeros((0, 2, 2))).semi_major.shape == (0,)


def test_95_percent_of_gaussian_samples_fall_inside():
    rng = np.random.default_rng(1)
    theta = 0.7
    cov = rotation(theta) @ np.diag([4.0, 0.3]) @ rotation(theta).T
    x = rng.multivariate_normal([0.0, 0.0], cov, size=200_000)
    e = ellipse(cov, confidence=0.95)
    # into the ellipse's own frame: u along the major axis
    u = x[:, 0] * np.cos(e.angle) + x[:, 1] * np.sin(e.angle)
    v = -x[:, 0] * np.sin(e.angle) + x[:, 1] * np.cos(e.angle)
    inside = (u / e.semi_major) ** 2 + (v / e.semi_minor) ** 2 <= 1.0
    assert inside.mean() == pytest.approx(0.95, abs=0.002)  # SE is 0.0005


@pytest.mark.parametrize("cov, conf, match", [
    (np.eye(3), 0.95, r"cov must be 2x2"),
    (np.zeros((4, 2)), 0.95, r"cov must have shape \[N, D, D\]"),
    (np.array([[1.0, 2.0], [2.0, 1.0]]), 0.95, "not positive semi-definite"),
    (np.array([[1.0, np.nan], [0.0, 1.0]]), 0.95, "cov has NaN"),
    (np.eye(2), 1.0, r"confidence must be in \(0, 1\)"),
    (np.eye(2), 0.0, "confidence must be"),
])
def test_bad_input(cov, conf, match):
    with pytest.raises(ValueError, match=match):
        ellipse(cov, conf)


def test_an_infinite_radius_is_the_whole_plane_and_nan_or_negative_is_refused():
    from calibrators.regions import radius_ellipse

    cov = np.array([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 0.0]]])
    el = radius_ellipse(cov, np.array([np.inf, 2.0]))
    assert el.semi_major[0] == np.inf and el.semi_minor[0] == np.inf
    assert (el.semi_major[1], el.semi_minor[1]) == (2.0, 0.0)
    assert np.isfinite(el.angle).all()
    el = radius_ellipse(cov[1:], np.array([np.inf]))   # inf·0 would be nan: still inf
    assert el.semi_minor[0] == np.inf
    for bad in (np.nan, -1.0):
        with pytest.raises(ValueError, match="radius must be >= 0"):
            radius_ellipse(cov[:1], np.array([bad]))
