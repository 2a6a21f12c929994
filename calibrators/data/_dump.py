"""The validation dump: detections of many frames plus the ground truth of the same frames.

This is the in-memory form of validation dump v1 (docs/formats.md). Constructing a `Dump`
validates it; every error names the key. Shapes:

    classes          [C]          class names in logit column order
    score_mode       str          "sigmoid" or "softmax"
    frame_ids        [F]  str     frame (sample) tokens
    det_frame        [N]  int     index into frame_ids
    det_logits       [N, L, C']   raw logits per decoder layer, last = final;
                                  C' = C (sigmoid) or C + 1 (softmax, last = no-object)
    det_boxes        [N, L, 9]    x y z w l h yaw vx vy per layer, last = final
    gt_frame         [G]  int     index into frame_ids
    gt_labels        [G]  int     index into classes
    gt_boxes         [G, 9]       same layout as det_boxes
    ego_translation  [F, 3] | None  ego position per frame; None = boxes are ego-frame
    det_cov          [N, D, D] | None  box covariance over cov_dims
    cov_dims         [D]  str     default ("x", "y")
    det_hyp_boxes    [N, H, 9] | None  final-layer box of each of H group regression heads
                                  (seed 001's multi-hypothesis output), same layout as det_boxes
    det_hyp_scores   [N, H] | None     group score of each hypothesis (summed class
                                  probabilities of the group's classes), >= 0
    det_label        [N] int | None    the class each detection asserts, index into classes;
                                  None = the arg-max of its final-layer logits. A detector
                                  that decodes the top-K (query, class) pairs (DETR3D's and
                                  PETR's NMS-free coder) gives one query several detections,
                                  one per class, with the same logits and boxes.

The two hypothesis arrays come together or not at all. `det_labels` / `det_scores` are the
label (given or arg-max) and its probability.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np

from calibrators.core.checks import (
    as_float_array,
    as_int_array,
    check_choice,
    check_covariances,
    check_index,
    check_length,
)
from calibrators.core.errors import FieldError
from calibrators.core.vocab import BOX_FIELDS, SCORE_MODES
from calibrators.covariance import check_hypotheses
from calibrators.scores import label_scores, predict


@dataclass(frozen=True, eq=False)
class Dump:
    """A validated validation dump (see the module docstring for every field's shape)."""

    classes: tuple[str, ...]
    score_mode: str
    frame_ids: np.ndarray
    det_frame: np.ndarray
    det_logits: np.ndarray
    det_boxes: np.ndarray
    gt_frame: np.ndarray
    gt_labels: np.ndarray
    gt_boxes: np.ndarray
    ego_translation: np.ndarray | None = None
    det_cov: np.ndarray | None = None
    cov_dims: tuple[str, ...] = field(default=("x", "y"))
    det_hyp_boxes: np.ndarray | None = None
    det_hyp_scores: np.ndarray | None = None
    det_label: np.ndarray | None = None

    def __post_init__(self) -> None:
        n_classes, n_frames = self._check_names()
        logits, boxes, det_frame = self._check_detections(n_classes, n_frames)
        gt_boxes, gt_frame, gt_labels = self._check_ground_truth(n_classes, n_frames)
        for name, value in (("det_logits", logits), ("det_boxes", boxes), ("det_frame", det_frame),
                            ("gt_boxes", gt_boxes), ("gt_frame", gt_frame),
                            ("gt_labels", gt_labels)):
            object.__setattr__(self, name, value)
        n = len(logits)
        self._check_ego(n_frames)
        self._check_covariance(n)
        self._check_hypotheses(n)
        self._check_label(n, n_classes)

    def _check_names(self) -> tuple[int, int]:
        """Validate and normalise `classes`, `score_mode` and `frame_ids`: (C, F)."""
        set_ = object.__setattr__
        classes = tuple(str(c) for c in np.asarray(self.classes).reshape(-1).tolist())
        if not classes:
            raise ValueError("classes must name at least one class")
        if len(set(classes)) != len(classes):
            raise ValueError("classes has duplicate names")
        set_(self, "classes", classes)
        check_choice("score_mode", str(self.score_mode), SCORE_MODES)
        set_(self, "score_mode", str(self.score_mode))
        frame_ids = np.asarray(self.frame_ids).astype(str).reshape(-1)
        if len(set(frame_ids.tolist())) != len(frame_ids):
            raise ValueError("frame_ids has duplicate tokens")
        set_(self, "frame_ids", frame_ids)
        return len(classes), len(frame_ids)

    def _check_detections(self, n_classes: int,
                          n_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The validated `det_logits [N, L, C']`, `det_boxes [N, L, 9]` and `det_frame [N]`."""
        logits = as_float_array("det_logits", self.det_logits, ndim=3)
        n, n_layers, width = logits.shape
        want = n_classes + (1 if self.score_mode == "softmax" else 0)
        if width != want:
            raise ValueError(f"det_logits has {width} columns but {self.score_mode} mode with "
                             f"{n_classes} classes needs {want}")
        if n_layers < 1:
            raise ValueError("det_logits must have at least one decoder layer (L >= 1)")
        boxes = as_float_array("det_boxes", self.det_boxes, ndim=3)
        if boxes.shape != (n, n_layers, 9):
            raise ValueError(f"det_boxes must have shape [{n}, {n_layers}, 9], got {boxes.shape}")
        det_frame = as_int_array("det_frame", self.det_frame)
        check_length("det_frame", det_frame, n, "det_logits")
        check_index("det_frame", det_frame, n_frames, "frames")
        return logits, boxes, det_frame

    def _check_ground_truth(self, n_classes: int,
                            n_frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The validated `gt_boxes [G, 9]`, `gt_frame [G]` and `gt_labels [G]`."""
        gt_boxes = as_float_array("gt_boxes", self.gt_boxes, ndim=2)
        if gt_boxes.shape[1:] != (9,):
            raise ValueError(f"gt_boxes must have shape [G, 9], got {gt_boxes.shape}")
        gt_frame = as_int_array("gt_frame", self.gt_frame)
        gt_labels = as_int_array("gt_labels", self.gt_labels)
        check_length("gt_frame", gt_frame, len(gt_boxes), "gt_boxes")
        check_length("gt_labels", gt_labels, len(gt_boxes), "gt_boxes")
        check_index("gt_frame", gt_frame, n_frames, "frames")
        check_index("gt_labels", gt_labels, n_classes, "classes")
        return gt_boxes, gt_frame, gt_labels

    def _check_ego(self, n_frames: int) -> None:
        """Validate the optional `ego_translation [F, 3]`."""
        if self.ego_translation is not None:
            ego = as_float_array("ego_translation", self.ego_translation, ndim=2)
            if ego.shape != (n_frames, 3):
                raise ValueError(f"ego_translation must have shape [{n_frames}, 3], "
                                 f"got {ego.shape}")
            object.__setattr__(self, "ego_translation", ego)

    def _check_covariance(self, n: int) -> None:
        """Validate `cov_dims` and the optional `det_cov [N, D, D]` over them."""
        cov_dims = tuple(str(d) for d in np.asarray(self.cov_dims).reshape(-1).tolist())
        for d in cov_dims:
            check_choice("cov_dims", d, BOX_FIELDS)
        if len(set(cov_dims)) != len(cov_dims) or not cov_dims:
            raise ValueError("cov_dims must name distinct box fields")
        object.__setattr__(self, "cov_dims", cov_dims)
        if self.det_cov is not None:
            cov = as_float_array("det_cov", self.det_cov, ndim=3)
            check_covariances("det_cov", cov, n=n, dim=len(cov_dims))
            object.__setattr__(self, "det_cov", cov)

    def _check_label(self, n: int, n_classes: int) -> None:
        """Validate the optional `det_label [N]`."""
        if self.det_label is not None:
            label = as_int_array("det_label", self.det_label)
            check_length("det_label", label, n, "det_logits")
            check_index("det_label", label, n_classes, "classes")
            object.__setattr__(self, "det_label", label)

    def _check_hypotheses(self, n: int) -> None:
        """Validate the optional `det_hyp_boxes [N, H, 9]` / `det_hyp_scores [N, H]` pair."""
        boxes, scores = self.det_hyp_boxes, self.det_hyp_scores
        if boxes is None and scores is None:
            return
        if boxes is None or scores is None:
            missing = "det_hyp_boxes" if boxes is None else "det_hyp_scores"
            given = "det_hyp_scores" if boxes is None else "det_hyp_boxes"
            raise FieldError(missing, f"{given} is given without {missing}; the hypothesis "
                                      "arrays come together")
        boxes, scores = check_hypotheses(boxes, scores, n, ("det_hyp_boxes", "det_hyp_scores"))
        object.__setattr__(self, "det_hyp_boxes", boxes)
        object.__setattr__(self, "det_hyp_scores", scores)

    # -- derived views -------------------------------------------------------------------
    @property
    def n_detections(self) -> int:
        return int(self.det_logits.shape[0])

    @property
    def n_layers(self) -> int:
        return int(self.det_logits.shape[1])

    @property
    def n_frames(self) -> int:
        return len(self.frame_ids)

    @property
    def n_hypotheses(self) -> int:
        """H, the box hypotheses per detection (0 without `det_hyp_boxes`)."""
        return 0 if self.det_hyp_boxes is None else int(self.det_hyp_boxes.shape[1])

    @cached_property
    def det_labels(self) -> np.ndarray:
        """`[N]` class of each detection: `det_label`, else the arg-max of its final-layer
        logits."""
        if self.det_label is not None:
            return self.det_label
        return predict(self.det_logits[:, -1], self.score_mode)[0]

    @cached_property
    def det_scores(self) -> np.ndarray:
        """`[N]` raw (uncalibrated) probability of each detection's class."""
        if self.det_label is not None:
            return label_scores(self.det_logits[:, -1], self.det_label, self.score_mode)
        return predict(self.det_logits[:, -1], self.score_mode)[1]

    @property
    def final_boxes(self) -> np.ndarray:
        """`[N, 9]` final-layer boxes."""
        return self.det_boxes[:, -1]

    def ego_xy(self, frame: np.ndarray) -> np.ndarray:
        """`[M, 2]` ego position for each entry of a frame-index array (zeros if ego-frame)."""
        if self.ego_translation is None:
            return np.zeros((len(frame), 2))
        return self.ego_translation[frame, :2]

    @cached_property
    def det_distance(self) -> np.ndarray:
        """`[N]` BEV distance of each final-layer box centre from the ego."""
        xy = self.final_boxes[:, :2] - self.ego_xy(self.det_frame)
        return np.hypot(xy[:, 0], xy[:, 1])

    @cached_property
    def gt_distance(self) -> np.ndarray:
        """`[G]` BEV distance of each ground-truth box centre from the ego."""
        xy = self.gt_boxes[:, :2] - self.ego_xy(self.gt_frame)
        return np.hypot(xy[:, 0], xy[:, 1])

    def select_frames(self, keep: np.ndarray) -> Dump:
        """A new dump with only the frames where the boolean `[F]` mask `keep` is True."""
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != (self.n_frames,):
            raise ValueError(f"keep must have shape [{self.n_frames}], got {keep.shape}")
        new_index = np.cumsum(keep) - 1
        d = keep[self.det_frame]
        g = keep[self.gt_frame]
        return replace(
            self,
            frame_ids=self.frame_ids[keep],
            ego_translation=None if self.ego_translation is None else self.ego_translation[keep],
            det_frame=new_index[self.det_frame[d]],
            det_logits=self.det_logits[d],
            det_boxes=self.det_boxes[d],
            det_cov=None if self.det_cov is None else self.det_cov[d],
            det_hyp_boxes=None if self.det_hyp_boxes is None else self.det_hyp_boxes[d],
            det_hyp_scores=None if self.det_hyp_scores is None else self.det_hyp_scores[d],
            det_label=None if self.det_label is None else self.det_label[d],
            gt_frame=new_index[self.gt_frame[g]],
            gt_labels=self.gt_labels[g],
            gt_boxes=self.gt_boxes[g],
        )

    def select_detections(self, keep: np.ndarray) -> Dump:
        """A new dump with only the detections where the boolean `[N]` mask `keep` is True
        (every per-detection array, the hypotheses included); frames and ground truth stay."""
        keep = np.asarray(keep, dtype=bool)
        if keep.shape != (self.n_detections,):
            raise ValueError(f"keep must have shape [{self.n_detections}], got {keep.shape}")

        def take(arr: np.ndarray | None) -> np.ndarray | None:
            return None if arr is None else arr[keep]

        return replace(self, det_frame=self.det_frame[keep], det_logits=self.det_logits[keep],
                       det_boxes=self.det_boxes[keep], det_cov=take(self.det_cov),
                       det_hyp_boxes=take(self.det_hyp_boxes),
                       det_hyp_scores=take(self.det_hyp_scores), det_label=take(self.det_label))


def concat_frames(dumps: list[Dump]) -> Dump:
    """One `Dump` of the frames of `dumps` in order (same classes, mode, layers and optional
    arrays): frame i of the second follows the last frame of the first, and so on."""
    offsets = np.cumsum([0] + [d.n_frames for d in dumps[:-1]])
    first = dumps[0]

    def cat(name: str) -> np.ndarray | None:
        values = [getattr(d, name) for d in dumps]
        return None if values[0] is None else np.concatenate(values)

    # Labels: given in any part -> given for all (the arg-max where a part has none).
    labels = None if all(d.det_label is None for d in dumps) else \
        np.concatenate([d.det_labels for d in dumps])

    return Dump(
        classes=first.classes, score_mode=first.score_mode, frame_ids=cat("frame_ids"),
        ego_translation=cat("ego_translation"), cov_dims=first.cov_dims,
        det_frame=np.concatenate([d.det_frame + o for d, o in zip(dumps, offsets, strict=True)]),
        det_logits=cat("det_logits"), det_boxes=cat("det_boxes"), det_cov=cat("det_cov"),
        det_hyp_boxes=cat("det_hyp_boxes"), det_hyp_scores=cat("det_hyp_scores"),
        det_label=labels,
        gt_frame=np.concatenate([d.gt_frame + o for d, o in zip(dumps, offsets, strict=True)]),
        gt_labels=cat("gt_labels"), gt_boxes=cat("gt_boxes"))
