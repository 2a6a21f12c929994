"""`Detections`: the one batch type at the calibrate boundary, each detection with its identity.

A front end turns what it received into `Detections` with an adapter (`from_dump`, and in
`calibrators.io`: `detections_from_arrow`, `detections_from_records`,
`detections_from_nuscenes`), calibrates it (`Detections.calibrate` ->
`CalibratedDetections`, which keeps the batch it came from) and writes the result with
`CalibratedDetections.to_records()`, `.to_arrow()` or `.to_nuscenes()`. Every output
detection carries its identity: its frame token plus its input row (or the user's
`detection_id`), so nothing is ever paired across representations by position.

Shapes (N detections, C' logit columns, L layers, D covariance dims, H hypotheses):

    frame_ids      [N]            frame (sample) token of each detection (str or int)
    rows           [N] int64      the detection's row in its input: the dump's detection
                                  index, the Arrow row, the record's position in the request,
                                  the box's position in its frame's list of a results document
    boxes          [N, 9]         final box x y z w l h yaw vx vy
    ego_xy         [N, 2]         ego position of the detection's frame (zeros: ego frame)
    logits         [N, C'] | None        final-layer logits
    layer_logits   [N, L, C'] | None     every decoder layer's logits (last = final)
    scores         [N] | None            the score of `labels` only
    labels         [N] int64 | None      the class each detection asserts (None: arg-max)
    covariances    [N, D, D] | None      given Σ over the profile's cov_dims
    layer_boxes    [N, L, 9] | None      every decoder layer's box (covariance source `layers`)
    hyp_boxes      [N, H, 9] | None      group heads' boxes, with hyp_scores [N, H]
    detection_ids  [N] | None            the user's id of each detection, echoed back
    sources        [N] dict | None       each input record's own keys, echoed back (a
                                         results document's boxes keep every key)
    frame_tokens   [F] | None            every frame of the input in order, frames without
                                         detections included (a results document lists them)

Exactly one of `logits`, `layer_logits`, `scores` is given (`scores` with `labels`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from calibrators.exceptions import FieldError

if TYPE_CHECKING:
    from calibrators.dump import Dump
    from calibrators.profile import CalibrationProfile
    from calibrators.serving import CalibratedDetections

__all__ = ["WIRE_NAMES", "Detections", "source_arrays"]

#: Argument of `CalibrationProfile.calibrate` -> the wire name of the same value (a JSON
#: detection's key, an Arrow request column). The one map every front end uses.
WIRE_NAMES = {"logits": "logits", "layer_logits": "layer_logits", "scores": "score",
              "labels": "label", "boxes": "box", "distances": "box",
              "covariances": "covariance", "layer_boxes": "layer_boxes",
              "ego_xy": "ego_translation", "hyp_boxes": "hypothesis_boxes",
              "hyp_scores": "hypothesis_scores"}

#: The array fields that are passed to `CalibrationProfile.calibrate` as they are.
_CALIBRATE_ARGS = ("logits", "layer_logits", "scores", "labels", "boxes", "ego_xy",
                   "covariances", "layer_boxes", "hyp_boxes", "hyp_scores")


@dataclass(frozen=True, eq=False)
class Detections:
    """N detections to calibrate, each with its identity (module docstring: every shape)."""

    frame_ids: np.ndarray
    rows: np.ndarray
    boxes: np.ndarray
    ego_xy: np.ndarray
    logits: np.ndarray | None = None
    layer_logits: np.ndarray | None = None
    scores: np.ndarray | None = None
    labels: np.ndarray | None = None
    covariances: np.ndarray | None = None
    layer_boxes: np.ndarray | None = None
    hyp_boxes: np.ndarray | None = None
    hyp_scores: np.ndarray | None = None
    detection_ids: Sequence[Any] | None = None
    sources: Sequence[dict[str, Any]] | None = None
    frame_tokens: Sequence[Any] | None = None

    def __post_init__(self) -> None:
        n = len(self.rows)
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name != "frame_tokens" and value is not None and len(value) != n:
                raise FieldError(WIRE_NAMES.get(f.name, f.name),
                                 f"{f.name} has {len(value)} rows but rows has {n}")

    def __len__(self) -> int:
        return len(self.rows)

    @classmethod
    def from_dump(cls, dump: Dump, cov_source: str) -> Detections:
        """The final-layer detections of `dump` (rows = detection index, frame ids = the
        dump's frame tokens) with every decoder layer's logits, the labels the dump asserts
        and the raw Σ of `cov_source` (`source_arrays`)."""
        return cls(frame_ids=np.asarray(dump.frame_ids)[dump.det_frame],
                   rows=np.arange(dump.n_detections, dtype=np.int64),
                   boxes=dump.final_boxes, ego_xy=dump.ego_xy(dump.det_frame),
                   layer_logits=dump.det_logits, labels=dump.det_label,
                   frame_tokens=list(np.asarray(dump.frame_ids).tolist()),
                   **source_arrays(dump, cov_source))

    def calibrate_arguments(self) -> dict[str, np.ndarray]:
        """The keyword arguments of `CalibrationProfile.calibrate` (the arrays given)."""
        return {k: getattr(self, k) for k in _CALIBRATE_ARGS if getattr(self, k) is not None}

    def take(self, index: np.ndarray) -> Detections:
        """The detections at `index [M]` (int positions), each keeping its identity."""
        index = np.asarray(index, dtype=np.int64)
        out: dict[str, Any] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None or f.name == "frame_tokens":
                continue
            out[f.name] = (value[index] if isinstance(value, np.ndarray)
                           else [value[i] for i in index.tolist()])
        return replace(self, **out)

    def calibrate(self, profile: CalibrationProfile, *, ellipse_confidence: float = 0.95,
                  levels: Sequence[float] | None = None) -> CalibratedDetections:
        """These detections calibrated with `profile` (`calibrators.serving`), in this order;
        the result keeps this batch (`.detections`) for its identity and boxes."""
        out = profile.calibrate(**self.calibrate_arguments(),
                                ellipse_confidence=ellipse_confidence, levels=levels)
        return replace(out, detections=self)


def source_arrays(dump: Dump, source: str) -> dict[str, np.ndarray | None]:
    """The keyword arguments of `CalibrationProfile.calibrate` that carry covariance `source`
    from `dump`: `covariances [N, D, D]` (given), `layer_boxes [N, L, 9]` (layers),
    `hyp_boxes [N, H, 9]` and `hyp_scores [N, H]` (hypotheses), nothing (none)."""
    if source == "given":
        return {"covariances": dump.det_cov}
    if source == "layers":
        return {"layer_boxes": dump.det_boxes}
    if source == "hypotheses":
        return {"hyp_boxes": dump.det_hyp_boxes, "hyp_scores": dump.det_hyp_scores}
    return {}
