"""Training samples from the simulated world: frames -> (points, Target), with augmentation.

Augmentation is a small random rotation about the ego's vertical axis (default +-5 deg),
an optional mirror across the x axis and a small global scaling, applied identically to
points and boxes (and to vector-valued point features). Every transform keeps the ego at
the origin, so range-dependent sensor effects stay where the sensor put them. The defaults
are deliberately mild: every training step sees new scenes (100 000 training seeds), so
there is nothing to over-fit, while full rotations or mirrors would erase real structure of
the world (the ego drives along +x on a road along x, traffic keeps right), which a first
lidar run with rotations in +-180 deg and mirrors paid for in heading and class accuracy.

Shapes: points [P, F] float32 (FEATURES order), Target(labels [G] int64, boxes [G, 9]).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from detectors.losses import Target

# Pairs of point features that are (x, y) components of a vector and rotate with the frame.
VECTOR_FEATURES: tuple[tuple[str, str], ...] = (("vx", "vy"), ("vx_comp", "vy_comp"))


class Sample(NamedTuple):
    """One training frame: `points [P, F]` and its ground truth."""

    points: Tensor
    target: Target


def frame_sample(frame: object, half_extent: float, min_points: int = 1) -> Sample:
    """Points and the ground truth the sensor can see: boxes inside the square BEV grid of
    half side `half_extent` with at least `min_points` of the frame's points (as mmdet3d's
    nuScenes `valid_flag`: a box without a single point is label noise to a detector)."""
    points = np.array(frame.sensor_frame.points, dtype=np.float32)  # type: ignore[attr-defined]
    boxes = np.array(frame.scene.boxes, dtype=np.float32)  # type: ignore[attr-defined]
    labels = np.array(frame.scene.labels, dtype=np.int64)  # type: ignore[attr-defined]
    n_points = np.asarray(frame.sensor_frame.gt_num_points)  # type: ignore[attr-defined]
    keep = (np.abs(boxes[:, 0]) < half_extent) & (np.abs(boxes[:, 1]) < half_extent)
    keep &= n_points >= min_points
    return Sample(torch.from_numpy(points),
                  Target(torch.from_numpy(labels[keep]), torch.from_numpy(boxes[keep])))


def augment(sample: Sample, features: Sequence[str], rng: np.random.Generator,
            max_rotation: float = math.radians(5.0),
            scale_range: tuple[float, float] = (0.97, 1.03), mirror: bool = False) -> Sample:
    """Randomly rotate, mirror (y -> -y) and scale one sample (points and boxes alike)."""
    angle = float(rng.uniform(-max_rotation, max_rotation))
    flip = bool(mirror and rng.random() < 0.5)
    scale = float(rng.uniform(*scale_range))
    c, s = math.cos(angle), math.sin(angle)
    rot = torch.tensor([[c, -s], [s, c]], dtype=torch.float32)
    sign = -1.0 if flip else 1.0

    points = sample.points.clone()
    xy = points[:, 0:2].clone()
    xy[:, 1] *= sign
    points[:, 0:2] = xy @ rot.T * scale
    points[:, 2] *= scale
    names = list(features)
    for fx, fy in VECTOR_FEATURES:
        if fx in names and fy in names:
            ix, iy = names.index(fx), names.index(fy)
            v = points[:, [ix, iy]].clone()
            v[:, 1] *= sign
            points[:, [ix, iy]] = v @ rot.T

    boxes = sample.target.boxes.clone()
    for a, b in ((0, 1), (7, 8)):
        v = boxes[:, [a, b]].clone()
        v[:, 1] *= sign
        boxes[:, [a, b]] = v @ rot.T
    boxes[:, 0:2] *= scale
    boxes[:, 2:6] *= scale
    boxes[:, 7:9] *= scale
    yaw = boxes[:, 6] * sign + angle
    boxes[:, 6] = torch.atan2(torch.sin(yaw), torch.cos(yaw))
    return Sample(points, Target(sample.target.labels.clone(), boxes))


class TrainSamples(torch.utils.data.Dataset):
    """Deterministic stream of augmented training samples, indexed by a global sample number.

    Sample k uses seed `seeds[perm_e[k % n]]` with epoch e = k // n and `perm_e` a permutation
    drawn from (`seed`, e), and augmentation drawn from (`seed`, k): resuming at any k gives
    the very same data as an uninterrupted run. `extra_objects` (mean extra objects per
    class, see `detectors.sim.make_scene`) over-samples rare classes for the samples before
    `extra_until` (default: all); later samples show the world's own frequencies (seed 001's
    fade-out of ground-truth sampling for the last part of training).

    `reuse` r > 1 shows every simulated scene r times, each with its own augmentation, `span`
    samples apart: samples are taken in blocks of r * span, and sample k of a block shows
    scene k % span of that block. The simulation is a third of a lidar training step's CPU
    time, so r = 2 buys ~20 % more steps for the same wall-clock; the repeats lie `span`
    samples (span / batch_size steps) apart, so a batch never holds one scene twice. A
    worker keeps each simulated scene until its last use (at most `span` scenes in memory),
    and a resumed run re-simulates what it needs: the data of sample k still depends only
    on (seed, k). A repeated scene keeps the object sampling of its first use.
    """

    def __init__(self, sensor: str, seeds: Sequence[int], features: Sequence[str],
                 half_extent: float, seed: int = 0, n_samples: int = 1 << 30,
                 augment_data: bool = True,
                 extra_objects: Mapping[str, float] | None = None,
                 extra_until: int | None = None, reuse: int = 1, span: int = 256) -> None:
        if reuse < 1 or span < 1:
            raise ValueError(f"reuse and span must be >= 1, got {reuse}, {span}")
        self.sensor = sensor
        self.seeds = np.asarray(list(seeds), dtype=np.int64)
        self.features = tuple(features)
        self.half_extent = half_extent
        self.seed = seed
        self.n_samples = n_samples
        self.augment_data = augment_data
        self.extra_objects = dict(extra_objects) if extra_objects else None
        self.extra_until = extra_until
        self.reuse = reuse
        self.span = span
        self._perm: dict[int, np.ndarray] = {}
        self._scenes: dict[int, Sample] = {}   # simulated, not augmented; until last use

    def __len__(self) -> int:
        return self.n_samples

    def scene_seed(self, k: int) -> int:
        n = len(self.seeds)
        epoch = k // n
        if epoch not in self._perm:
            self._perm = {epoch: np.random.default_rng([self.seed, epoch]).permutation(n)}
        return int(self.seeds[self._perm[epoch][k % n]])

    def extra_for(self, k: int) -> dict[str, float] | None:
        """The object sampling of sample `k` (None once it has faded out)."""
        if self.extra_until is not None and k >= self.extra_until:
            return None
        return self.extra_objects

    def scene_use(self, k: int) -> tuple[int, int]:
        """Sample `k` -> (scene number j, use 0..reuse-1); use 0 is sample `first_sample(j)`
        (with reuse 1, j = k)."""
        block, offset = divmod(k, self.reuse * self.span)
        use, slot = divmod(offset, self.span)
        return block * self.span + slot, use

    def first_sample(self, j: int) -> int:
        """The sample that shows scene `j` first."""
        block, slot = divmod(j, self.span)
        return block * self.reuse * self.span + slot

    def _scene(self, k: int) -> Sample:
        """The (not augmented) simulated scene sample `k` shows."""
        from detectors.sim import make_frame

        j, use = self.scene_use(k)
        sample = self._scenes.pop(j, None) if use == self.reuse - 1 else self._scenes.get(j)
        if sample is None:
            first = self.first_sample(j)
            sample = frame_sample(make_frame(self.scene_seed(j), self.sensor,
                                             self.extra_for(first)), self.half_extent)
            if use < self.reuse - 1:
                self._scenes[j] = sample
        return sample

    def __getitem__(self, k: int) -> Sample:
        sample = self._scene(k)
        if self.augment_data:
            rng = np.random.default_rng([self.seed, 1, k])
            sample = augment(sample, self.features, rng)
        return sample


def collate(samples: list[Sample]) -> list[Sample]:
    """Keep a batch as a list (point clouds differ in size)."""
    return samples
