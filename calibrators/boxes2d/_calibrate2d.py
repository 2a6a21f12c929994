"""Serving a 2-D profile: `calibrate_2d(profile, detections, levels)` gives every detection its
calibrated score and, per level, its box region, in the input's row order.

- score: the profile's `ScoreStage2D` on the label's logit (`logits` read in the profile's
  `score_mode`, or `logit(score)` for a profile fit on scores; a request's logits are then not
  read). A `position` stage reads the box relative to its image: `image_size [N, 2]`, or the
  profile's own `image_size` when the fit images all shared one.
- regions: the profile's `ConformalBoxes` at `levels` (default `DEFAULT_LEVELS`), scaled by
  each edge's σ from the spread of the detection's `layer_boxes` when the profile's regions
  are `scaled` (`edge_covariance` with the profile's `min_sigma`), or by its fitted edge-error
  scale when they are `adaptive` (`EdgeErrorScale`, which may read the layer boxes' spread
  and the image size).

A bad input raises `FieldError` naming the field (and row): a category the profile does not
know (`category_id`), missing logits or layer boxes, a bad level.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from calibrators.boxes2d._boxes import Detections2D
from calibrators.boxes2d._coco_write import coco_results, write_coco_results
from calibrators.boxes2d._conformal_boxes import BoxRegions
from calibrators.boxes2d._layer_spread import edge_covariance, edge_sigma
from calibrators.boxes2d._profile2d import Profile2D
from calibrators.boxes2d._score_inputs import score_inputs
from calibrators.core.checks import as_float_array, check_length
from calibrators.core.defaults import DEFAULT_LEVELS
from calibrators.core.errors import FieldError
from calibrators.regions import check_levels

__all__ = ["Calibrated2D", "calibrate_2d", "served_sigma"]


@dataclass(frozen=True, eq=False)
class Calibrated2D:
    """N calibrated 2-D detections, row i being input row i.

    detections   Detections2D [N]   the input (its `score` is the detector's raw score)
    score [N]    float64            the calibrated probability of being a true positive
    regions      BoxRegions | None  inner / outer boxes `[N, Q, 4]` per level, each with its
                                    guarantee and calibration count (None: none served)
    """

    detections: Detections2D
    score: np.ndarray
    regions: BoxRegions | None

    def __len__(self) -> int:
        return len(self.score)

    def records(self) -> list[dict[str, Any]]:
        """The COCO results records (`coco_results`): calibrated `score`, `score_raw` and one
        `region_<q>` per level."""
        return coco_results(self.detections, self.score, self.regions)

    def write(self, path: str | os.PathLike[str]) -> None:
        """Write `records()` as a COCO results file (`write_coco_results`, one rename)."""
        write_coco_results(path, self.detections, self.score, self.regions)


def calibrate_2d(profile: Profile2D, detections: Detections2D,
                 levels: Sequence[float] | None = None,
                 image_size: np.ndarray | None = None) -> Calibrated2D:
    """Calibrate `detections [N]` with a 2-D `profile` (module docstring). `levels`: the
    region levels (None: `DEFAULT_LEVELS` when the profile has regions, none otherwise; given
    to a profile without regions, a FieldError). `image_size [N, 2]`: each detection's image
    width and height (pixels), read by a `position` score stage and by adaptive regions
    whose scale reads the image border (`Profile2D.reads_image_size`); None: the profile's
    own `image_size`."""
    if not isinstance(profile, Profile2D):
        raise FieldError("profile", "profile must be a Profile2D (a 2-D profile)")
    if not isinstance(detections, Detections2D):
        raise FieldError("detections", "detections must be a Detections2D")
    z, labels = _score_inputs(profile, detections)
    stage = profile.score_stage
    size = _image_size(profile, image_size, len(detections)) \
        if profile.reads_image_size else None
    score = stage.transform(z, labels, size if stage.uses_position else None, detections.bbox)
    regions = None
    if profile.box_regions is not None:
        q = check_levels(DEFAULT_LEVELS if levels is None else levels)
        regions = profile.box_regions.serve(detections.bbox, detections.category_id,
                                            served_sigma(profile, detections, size), q)
    elif levels is not None:
        raise FieldError("levels", "this 2-D profile serves no box regions (it was fit "
                                   "without a calibration part): leave levels out")
    return Calibrated2D(detections, score, regions)


def served_sigma(profile: Profile2D, detections: Detections2D,
                 image_size: np.ndarray | None = None) -> np.ndarray | None:
    """`[N, 4]` σ of each box edge the profile's regions divide by: the spread of the
    `layer_boxes` (scaled), the fitted edge-error scale (adaptive), or None (additive).
    `image_size [N, 2]` as `calibrate_2d` takes it. FieldError naming `layer_boxes` or
    `image_size` when what the regions read is missing."""
    kind = profile.region_score
    if kind is None or kind == "additive":
        return None
    if len(detections) == 0:
        return np.zeros((0, 4))
    scale = profile.error_scale
    layers = detections.layer_boxes
    if kind == "scaled" or scale.uses_layer_sigma:
        if layers is None or layers.shape[1] < 2:
            raise FieldError("layer_boxes", "this profile's box regions read the spread of "
                                            "the decoder layers' boxes: send each detection's "
                                            "layer_boxes, L >= 2 boxes [x, y, w, h]", row=0)
    if kind == "scaled":
        return edge_sigma(edge_covariance(layers, profile.regions["min_sigma"]))
    size = _image_size(profile, image_size, len(detections)) if scale.uses_image_size \
        else None
    spread = edge_sigma(edge_covariance(layers, 0.0)) if scale.uses_layer_sigma else None
    return scale.predict(detections.bbox, detections.score, spread, size)


def _score_inputs(profile: Profile2D, detections: Detections2D) -> tuple[np.ndarray,
                                                                          np.ndarray]:
    """The label's logit and class index, read as the profile was fit."""
    if profile.score_mode is None or len(detections) == 0:   # an empty batch has no logits
        plain = detections if detections.logits is None else replace(detections, logits=None)
        return score_inputs(plain, profile.category_ids)
    if detections.logits is None:
        raise FieldError("logits", f"this profile was fit on {profile.score_mode} logits: "
                                   "send each detection's logits, one per category in the "
                                   "profile's order")
    return score_inputs(detections, profile.category_ids, profile.score_mode)


def _image_size(profile: Profile2D, image_size: np.ndarray | None, n: int) -> np.ndarray:
    if image_size is not None:
        size = as_float_array("image_size", image_size, ndim=2)
        if size.shape[1:] != (2,):
            raise FieldError("image_size", f"image_size must have shape [N, 2] (width, "
                                           f"height), got {size.shape}")
        check_length("image_size", size, n, "detections")
        return size
    if profile.image_size is None:
        raise FieldError("image_size", "this profile reads where each box lies in its image "
                                       "(its score calibrator or box regions): give each "
                                       "image's width and height")
    return np.tile(np.asarray(profile.image_size, dtype=np.float64), (n, 1))
