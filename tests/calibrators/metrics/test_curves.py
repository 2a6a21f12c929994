import json

import numpy as np
import pytest
from scipy import stats

from calibrators import metrics


def _dense_area(x, y, n=2_000_001):
    """∫|y(t) − t| dt of the linear interpolation, by a fine trapezoid rule."""
    t = np.linspace(0.0, 1.0, n)
    return float(np.trapezoid(np.abs(np.interp(t, x, y) - t), t))


def _shoelace_area(x, y):
    """Area between (x, y) and the diagonal: split at crossings, sum shoelace polygons."""
    pts = [(x[0], y[0])]
    for i in range(len(x) - 1):
        d0, d1 = y[i] - x[i], y[i + 1] - x[i + 1]
        if d0 * d1 < 0:
            s = d0 / (d0 - d1)
            cx = x[i] + s * (x[i + 1] - x[i])
            pts.append((cx, cx))
        pts.append((x[i + 1], y[i + 1]))
    total, run = 0.0, [pts[0]]
    for p in pts[1:]:
        run.append(p)
        if p[0] == p[1] or p is pts[-1]:  # on the diagonal (a crossing) or the end
            if len(run) > 1:
                poly = run + [(px, px) for px, _ in reversed(run)]
                xs, ys = np.array(poly).T
                total += abs(np.dot(xs, np.roll(ys, -1)) - np.dot(ys, np.roll(xs, -1))) / 2
            run = [p]
    return total


def _utb_interval_proportions(r, s, m):
    """uncertainty-toolbox's vectorised interval proportions, with an [N, M] matrix."""
    p = np.linspace(0, 1, m)
    z = (r / s)[:, None]
    inside = (z >= stats.norm.ppf(0.5 - p / 2)) & (z <= stats.norm.ppf(0.5 + p / 2))
    return p, inside.sum(axis=0) / len(r)


def test_curve_matches_the_toolbox_definition():
    rng = np.random.default_rng(0)
    s = rng.uniform(0.2, 2.0, 3000)
    r = rng.standard_t(4, 3000) * s
    curve = metrics.average_calibration_curve(r, s, n_bins=37)
    p, obs = _utb_interval_proportions(r, s, 37)
    np.testing.assert_array_equal(curve.expected, p)
    np.testing.assert_array_equal(curve.observed, obs)
    assert curve.observed[0] == 0.0 and curve.observed[-1] == 1.0
    d = curve.to_dict()
    assert len(d["expected"]) == 37
    json.dumps(d, allow_nan=False)


def test_exact_gaussians_have_near_zero_area():
    rng = np.random.default_rng(1)
    s = rng.uniform(0.1, 5.0, 100_000)
    r = rng.normal(size=s.size) * s
    assert metrics.miscalibration_area(r, s) < 0.005


def test_halved_std_has_the_closed_form_area():
    rng = np.random.default_rng(2)
    s = rng.uniform(0.1, 5.0, 100_000)
    r = rng.normal(size=s.size) * s
    curve = metrics.average_calibration_curve(r, s / 2.0)
    area = metrics.miscalibration_area(r, s / 2.0)
    # with σ halved, z = 2 Z: obs(p) = 2 Φ(Φ⁻¹(0.5 + p/2) / 2) − 1, below the diagonal
    p = curve.expected
    closed = 2 * stats.norm.cdf(stats.norm.ppf(0.5 + p / 2) / 2) - 1
    np.testing.assert_allclose(curve.observed, closed, atol=0.01)
    assert area > 0.15
    assert area == pytest.approx(_dense_area(p, closed), abs=0.005)
    assert area == pytest.approx(_dense_area(p, curve.observed), abs=1e-6)
    assert area == pytest.approx(_shoelace_area(p, curve.observed), abs=1e-12)


def test_area_with_a_crossing_matches_independent_integrations():
    # half the residuals are 0 (always inside), half at |z| = 5 (inside only at p = 1):
    # the curve is 0.5 until the last point, crossing the diagonal at p = 0.5
    r = np.r_[np.zeros(50), np.full(25, 5.0), np.full(25, -5.0)]
    s = np.ones(100)
    curve = metrics.average_calibration_curve(r, s, n_bins=11)
    np.testing.assert_allclose(curve.observed, [0.5] * 10 + [1.0])
    area = metrics.miscalibration_area(r, s, n_bins=11)
    # ∫_0^0.9 |0.5 − p| + last segment from (0.9, 0.5) to (1, 1): |d| 0.4 → 0, area 0.02
    hand = 0.125 + 0.5 * 0.4 * 0.4 + 0.02
    assert area == pytest.approx(hand, abs=1e-12)
    assert area == pytest.approx(_shoelace_area(curve.expected, curve.observed), abs=1e-12)
    assert area == pytest.approx(_dense_area(curve.expected, curve.observed), abs=1e-7)


def test_area_matches_the_toolbox_polygon_procedure():
    shapely = pytest.importorskip("shapely")
    from shapely.ops import polygonize, unary_union

    rng = np.random.default_rng(3)
    s = rng.uniform(0.5, 1.5, 2000)
    r = np.r_[rng.normal(size=1000) * 0.5, rng.normal(size=1000) * 2.0] * s  # crosses
    curve = metrics.average_calibration_curve(r, s)
    x, y = curve.expected, curve.observed
    ring = list(zip(x, y, strict=True)) + list(zip(x[::-1], x[::-1], strict=True))
    ring.append(ring[0])
    faces = polygonize(unary_union(shapely.geometry.LineString(ring)))
    expected = sum(face.area for face in faces)
    assert metrics.miscalibration_area(r, s) == pytest.approx(expected, abs=1e-12)


# ---------------------------------------------------------------- bad input

_R = [0.1, -0.4, 0.3]
_S = [1.0, 0.5, 2.0]

BAD = [
    ("std zero", (_R, [1.0, 0.0, 1.0]), {}, "std_1d must be > 0; entry 1 is 0.0"),
    ("std negative", (_R, [1.0, 1.0, -2.0]), {}, "std_1d must be > 0; entry 2 is -2.0"),
    ("std NaN", (_R, [np.nan, 1.0, 1.0]), {}, "std_1d has NaN at index 0"),
    ("residual Inf", ([0.1, np.inf, 0.0], _S), {}, "residuals_1d has Inf at index 1"),
    ("residual 2-D", ([[0.1, 0.2, 0.3]], _S), {}, "residuals_1d must have 1 dimensions"),
    ("length", (_R, [1.0, 1.0]), {}, "std_1d has 2 rows but residuals_1d has 3"),
    ("empty", ([], []), {}, "residuals_1d is empty"),
    ("n_bins 1", (_R, _S), {"n_bins": 1}, "n_bins must be at least 2"),
    ("n_bins float", (_R, _S), {"n_bins": 10.0}, "n_bins must be an integer"),
]


@pytest.mark.parametrize("fn", [metrics.average_calibration_curve, metrics.miscalibration_area])
@pytest.mark.parametrize("args, kwargs, message", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_input_raises_named_value_error(fn, args, kwargs, message):
    with pytest.raises(ValueError, match=message):
        fn(*args, **kwargs)
