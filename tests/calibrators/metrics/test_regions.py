"""Region metrics on hand-computable cases: coverage, coverage table, area, class-wise ECE."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from calibrators.metrics import (
    classwise_ece,
    coverage_table,
    ellipse_coverage,
    expected_calibration_error,
    mean_ellipse_area,
)

MD = np.array([0.5, 1.0, 2.0, 3.0])


def test_ellipse_coverage_counts_the_boundary_and_infinite_radii():
    radii = np.array([[1.0, 2.5, math.inf]] * 4)
    result = ellipse_coverage(MD, radii, [0.5, 0.9, 0.99])
    np.testing.assert_array_equal(result.coverage, [0.5, 0.75, 1.0])
    assert result.count == 4
    assert result.to_dict() == {"levels": [0.5, 0.9, 0.99], "coverage": [0.5, 0.75, 1.0],
                                "count": 4}


def test_coverage_table_per_class_and_distance_bin():
    md = np.array([0.5, 1.5, 0.5, 1.5, 0.5, 0.5])
    radii = np.ones((6, 1))
    classes = np.array(["car", "car", "car", "car", "ped", "ped"])
    d = np.array([1.0, 2.0, 20.0, 40.0, 5.0, 100.0])
    table = coverage_table(md, radii, [0.9], classes, d, distance_edges=(0, 15, 30, math.inf))
    assert table.count == 6 and table.overall.tolist() == [4 / 6]
    rows = [(r["class"], r["bin"], r["count"], r["coverage"]) for r in table.rows]
    assert rows == [("car", 0, 2, [0.5]), ("car", 1, 1, [1.0]), ("car", 2, 1, [0.0]),
                    ("ped", 0, 1, [1.0]), ("ped", 2, 1, [1.0])]
    data = json.loads(json.dumps(table.to_dict(), allow_nan=False))
    assert data["distance_edges"] == [0.0, 15.0, 30.0, None]
    assert data["rows"][2]["distance_range"] == [30.0, None]


def test_mean_ellipse_area():
    cov = np.array([np.diag([4.0, 1.0]), np.eye(2)])
    radii = np.array([[2.0, 1.0], [1.0, math.inf]])
    # pi r² sqrt(det): [pi·4·2, pi·1·1] and [pi·1·2, inf]
    np.testing.assert_allclose(mean_ellipse_area(cov, radii),
                               [(8 * np.pi + np.pi) / 2, np.inf])
    rotated = np.array([[[2.0, 1.0], [1.0, 2.0]]])  # det 3
    assert mean_ellipse_area(rotated, [[1.0]])[0] == pytest.approx(np.pi * np.sqrt(3.0))


def test_classwise_ece_uses_the_library_ece():
    scores = np.array([0.8] * 5 + [0.9] * 2 + [0.3, 0.6, 0.65])
    tp = np.array([1, 1, 1, 1, 0, 0, 0, 1, 0, 1], dtype=bool)
    labels = np.array([0] * 5 + [1] * 2 + [3] * 3)
    out = classwise_ece(scores, tp, labels, ["car", "truck", "bus", "ped"])
    assert out["car"] == pytest.approx(0.0, abs=1e-12)
    assert out["truck"] == pytest.approx(0.9)
    assert out["bus"] is None
    assert out["ped"] == pytest.approx(expected_calibration_error(scores[7:], tp[7:]))


def test_validation_names_the_argument():
    with pytest.raises(ValueError, match="levels"):
        ellipse_coverage(MD, np.ones((4, 1)), [1.0])
    with pytest.raises(ValueError, match="radii has 2 columns"):
        ellipse_coverage(MD, np.ones((4, 2)), [0.9])
    with pytest.raises(ValueError, match="radii"):
        ellipse_coverage(MD, np.full((4, 1), np.nan), [0.9])
    with pytest.raises(ValueError, match="mahalanobis"):
        ellipse_coverage(-MD, np.ones((4, 1)), [0.9])
    with pytest.raises(ValueError, match="distances"):
        coverage_table(MD, np.ones((4, 1)), [0.9], np.zeros(4, int), np.ones(3))
    with pytest.raises(ValueError, match="covariances"):
        mean_ellipse_area(np.ones((1, 3, 3)), [[1.0]])
    with pytest.raises(ValueError, match="labels"):
        classwise_ece([0.5], [True], [2], ["car"])
    with pytest.raises(ValueError, match="scores"):
        classwise_ece([1.5], [True], [0], ["car"])
