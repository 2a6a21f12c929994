"""`detcal show`: a bird's-eye view, raw or with a profile of any covariance source."""

from __future__ import annotations

import pytest
import torch

from calibrators.data import synthetic_dump
from calibrators.fit import fit_profile
from detectors import build_detector
from detectors.show import render_frame


@pytest.fixture(scope="module")
def lidar():
    torch.set_num_threads(1)
    return build_detector("lidar")


@pytest.mark.parametrize("cov_source", [None, "given", "layers", "none"])
def test_show_draws_a_png_with_and_without_a_profile(lidar, tmp_path, cov_source):
    profile = None
    if cov_source is not None:
        profile = fit_profile(synthetic_dump(n_frames=20, seed=3), cov_source=cov_source)
    out = render_frame(lidar, 200_000, tmp_path / "scene.png", profile=profile)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
