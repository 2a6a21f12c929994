"""`detectors.panels`: the panels shared by the report, `detcal show` and the dashboard."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calibrators import ellipse
from detectors.panels import Curve, panel_grid, pyplot
from detectors.panels.bev import BevStyle, bev_panel
from detectors.panels.calibration_curve import calibration_curve_panel
from detectors.panels.reliability import reliability_panel

ROOT = Path(__file__).resolve().parents[2]
STYLE = BevStyle(point_color="0.7", point_size=(0.5, 3), gt_color="tab:green", box_width=1.0,
                 label_dy=1.0, label_colored=False)


@pytest.fixture
def ax():
    plt = pyplot()
    fig, axes = plt.subplots()
    yield axes
    plt.close(fig)


def _boxes(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    boxes = np.zeros((n, 9))
    boxes[:, :2] = rng.uniform(-40, 40, (n, 2))
    boxes[:, 3:6] = rng.uniform(1, 4, (n, 3))
    boxes[:, 6] = rng.uniform(-3, 3, n)
    return boxes


def test_importing_the_panels_loads_no_matplotlib_torch_or_simulator():
    code = ("import json, sys\n"
            "import detectors.panels.bev, detectors.panels.reliability\n"
            "import detectors.panels.calibration_curve\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
            "('matplotlib', 'torch') or m.startswith('detectors.sim'))))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, timeout=120, check=True)
    assert json.loads(proc.stdout) == []


def test_bev_panel_draws_outlines_texts_ellipses_and_the_ego(ax):
    gt, det = _boxes(3, 0), _boxes(4, 1)
    cov = np.tile(np.eye(2), (4, 1, 1))
    cov[2] = 0.0  # a zero-size ellipse is left out
    bev_panel(ax, np.zeros((10, 3)), gt, det, ["a", "b", "c", "d"], ellipse(cov),
              color="tab:blue", ellipse_color="tab:red", half=50.0, style=STYLE)
    assert len(ax.lines) == 3 + 4 + 1
    assert [t.get_text() for t in ax.texts] == ["a", "b", "c", "d"]
    assert len(ax.patches) == 3
    assert ax.get_xlim() == (-50.0, 50.0)
    with pytest.raises(ValueError):
        bev_panel(ax, np.zeros((0, 3)), gt, det, ["one text"], None, color="k",
                  ellipse_color="k", half=1.0, style=STYLE)


def test_reliability_panel_leaves_out_empty_bins(ax):
    conf = np.array([0.1, np.nan, 0.5, 0.9])
    acc = np.array([0.2, 0.3, np.nan, 0.8])
    reliability_panel(ax, [Curve(conf, acc, {"label": "m"})], "car")
    diagonal, curve = ax.lines
    assert np.array_equal(curve.get_xdata(), [0.1, 0.9])
    assert curve.get_label() == "m"
    assert ax.get_title() == "car"


def test_calibration_curve_panel_says_when_there_is_no_covariance(ax):
    calibration_curve_panel(ax, [], "x")
    assert [t.get_text() for t in ax.texts] == ["no covariance"]


def test_panel_grid_hides_the_spare_cells():
    fig, axes = panel_grid(7, 5, 1.0, 1.0)
    assert axes.shape == (2, 5)
    assert [a.get_visible() for a in axes.flat] == [True] * 7 + [False] * 3
    pyplot().close(fig)
