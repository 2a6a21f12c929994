"""Camera frames as network inputs and targets, and the on-the-fly training stream.

One frame is six images (`detectors.sim.CAMERA_NAMES` order), fed as a batch of six: the
backbone, encoder and decoder treat every image alone (a panorama would let objects cross
the seams, but costs the same convolutions and needs its own target bookkeeping; the seams
are where 24 % of the boxes are truncated either way).

    frame_inputs(images, config)  -> [6, 4, H_in, W_in] float32
    frame_targets(truth, config)  -> 6 ImageTarget (labels [G_i], boxes [G_i, 4] cx cy w h)

`TrainFrames[i]` is training sample i: scene `SPLITS["train"][i]` rendered (with rare-class
object sampling before `extra_until`), each image mirrored left-right with probability 1/2
from `default_rng([seed, FLIP_STREAM, i])`: the data of sample i depends on (seed, i) only.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
import torch
from torch import Tensor

from detectors.boxer2d.boxes import coco_to_cxcywh
from detectors.boxer2d.config import Boxer2DConfig
from detectors.boxer2d.criterion import ImageTarget
from detectors.sim import CameraImages, ImageTruth, make_image_frame

FLIP_STREAM = 2024


def frame_inputs(images: CameraImages, config: Boxer2DConfig) -> Tensor:
    """The six images of a frame -> `[6, 4, H_in, W_in]`: colour - 0.5, depth / range, the
    rows below the image (padding to `input_size`) zero."""
    w_in, h_in = config.input_size
    c, h, w, _ = images.rgb.shape
    out = np.zeros((c, 4, h_in, w_in), dtype=np.float32)
    out[:, :3, :h, :w] = images.rgb.transpose(0, 3, 1, 2) - 0.5
    out[:, 3, :h, :w] = images.depth / config.depth_range
    return torch.from_numpy(out)


def frame_targets(truth: ImageTruth, config: Boxer2DConfig, n_images: int = 6
                  ) -> list[ImageTarget]:
    """A frame's 2-D ground truth -> one `ImageTarget` per image (boxes normalised by
    `input_size`)."""
    w_in, h_in = config.input_size
    boxes = coco_to_cxcywh(torch.from_numpy(np.array(truth.bbox)), w_in, h_in)
    labels = torch.from_numpy(np.array(truth.label))
    camera = np.asarray(truth.camera)
    return [ImageTarget(labels[camera == c], boxes[camera == c]) for c in range(n_images)]


def mirror(inputs: Tensor, targets: list[ImageTarget], flip: Sequence[bool]
           ) -> tuple[Tensor, list[ImageTarget]]:
    """Mirror image i of `inputs [N, 4, H, W]` and its target left-right where `flip[i]`."""
    inputs = inputs.clone()
    out = []
    for i, (t, f) in enumerate(zip(targets, flip, strict=True)):
        if f:
            inputs[i] = inputs[i].flip(-1)
            boxes = t.boxes.clone()
            boxes[:, 0] = 1.0 - boxes[:, 0]
            t = ImageTarget(t.labels, boxes)
        out.append(t)
    return inputs, out


class TrainFrames(torch.utils.data.Dataset):
    """Training samples generated on the fly; see the module docstring."""

    def __init__(self, config: Boxer2DConfig, seeds: Sequence[int], seed: int,
                 extra_objects: Mapping[str, float] | None = None,
                 extra_until: int = 0) -> None:
        self.config = config
        self.seeds = seeds
        self.seed = seed
        self.extra_objects = extra_objects
        self.extra_until = extra_until

    def __len__(self) -> int:
        return len(self.seeds)

    def __getitem__(self, i: int) -> tuple[Tensor, list[ImageTarget]]:
        extra = self.extra_objects if i < self.extra_until else None
        frame = make_image_frame(int(self.seeds[i]), extra)
        inputs = frame_inputs(frame.images, self.config)
        targets = frame_targets(frame.truth, self.config)
        flip = np.random.default_rng([self.seed, FLIP_STREAM, i]).random(len(targets)) < 0.5
        return mirror(inputs, targets, flip.tolist())


def collate_frames(batch: list[tuple[Tensor, list[ImageTarget]]]
                   ) -> tuple[Tensor, list[ImageTarget]]:
    """B samples -> (`[6B, 4, H_in, W_in]`, 6B targets), frame-major."""
    return torch.cat([x for x, _ in batch]), [t for _, ts in batch for t in ts]
