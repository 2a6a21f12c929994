"""Training samples: scene reuse (each simulated scene shown `reuse` times, `span` samples
apart, each time with its own augmentation) keeps the data a function of (seed, k)."""

from __future__ import annotations

import pytest
import torch

from detectors.samples import TrainSamples
from detectors.sim import SPLITS

SEEDS = SPLITS["train"][:50]


def _samples(**kw: object) -> TrainSamples:
    return TrainSamples("radar5", SEEDS, ("x", "y", "z"), 51.2, seed=3, **kw)  # type: ignore


def test_scenes_repeat_span_apart_and_never_within_a_span() -> None:
    data = _samples(reuse=3, span=4)
    uses = [data.scene_use(k) for k in range(36)]
    for k, (j, use) in enumerate(uses):
        assert data.first_sample(j) + use * 4 == k
    for start in range(0, 33):
        window = [j for j, _ in uses[start:start + 4]]
        assert len(set(window)) == 4
    assert sorted(j for j, _ in uses) == sorted(list(range(12)) * 3)
    with pytest.raises(ValueError, match="reuse"):
        _samples(reuse=0)


def test_a_repeat_is_the_same_scene_augmented_anew_and_resumes_identically() -> None:
    data = _samples(reuse=2, span=2)
    first, second = data[0], data[2]     # scene 0, uses 0 and 1
    assert torch.equal(first.target.labels, second.target.labels)
    assert first.points.shape == second.points.shape
    assert not torch.equal(first.points, second.points)   # another rotation and scale
    # a resumed run (nothing cached) re-simulates the scene and gets the very same sample
    fresh = _samples(reuse=2, span=2)
    torch.testing.assert_close(fresh[2].points, second.points, rtol=0, atol=0)
    torch.testing.assert_close(fresh[2].target.boxes, second.target.boxes, rtol=0, atol=0)
    # the first uses are what a run without reuse sees
    plain = _samples()
    torch.testing.assert_close(plain[1].points, data[1].points, rtol=0, atol=0)


def test_the_cache_holds_a_scene_only_until_its_last_use() -> None:
    data = _samples(reuse=2, span=3)
    for k in range(12):
        data[k]
        assert len(data._scenes) <= 3
    assert data._scenes == {}
