"""When `class_scores` is given, exactly as docs/api.md says: with logits (or layer logits)
under a one-temperature score stage; null for score + label input and for every per-class
score stage (those map the label's logit alone)."""

from __future__ import annotations

import numpy as np
import pytest

from calibrators import FitOptions, fit_profile
from calibrators.core.vocab import SCORE_METHODS
from calibrators.data import synthetic_dump


@pytest.fixture(scope="module")
def dump():
    return synthetic_dump(n_frames=30, seed=3)


@pytest.mark.parametrize("method", SCORE_METHODS)
def test_class_scores_follow_the_documented_rule(dump, method):
    profile = fit_profile(dump, FitOptions(score_method=method), cov_source="given")
    args = {"boxes": dump.final_boxes, "covariances": dump.det_cov}
    out = profile.calibrate(logits=dump.det_logits[:, -1], **args)
    layers = profile.calibrate(layer_logits=dump.det_logits, **args)
    scores_only = profile.calibrate(scores=dump.det_scores, labels=dump.det_labels, **args)
    assert scores_only.class_scores is None
    if method == "temperature":
        n = len(out)
        for res in (out, layers):
            assert res.class_scores is not None
            assert res.class_scores.shape == (n, len(profile.classes))
            np.testing.assert_allclose(res.class_scores[np.arange(n), res.labels], res.scores)
    else:
        assert out.class_scores is None and layers.class_scores is None
