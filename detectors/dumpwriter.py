"""Validation dumps of a detector over simulated frames (validation dump v1, docs/formats.md).

`build_dump` runs a sensor's detector over scenes of a split and collects, per kept query,
the logits and boxes of every decoder layer, an optional box covariance over (x, y), and the
ground truth of the same frames. Covariance sources (`cov_source`, one of
`detectors.vocab.DUMP_COV_SOURCES`):

- "layers" (default): sample covariance of the query's box across decoder layers (thesis);
- "attention": seed 000's attention covariance C_K of the final layer's top-K attention,
  plus the variance of a uniform position within one token cell (cell^2 / 12 per axis) so
  that a query attending to a single cell still gets a proper (positive definite) covariance;
- "none": no det_cov (calibration then fits depth scaling from Sigma = 0).

Ground truth (`gt_filter`), as nuScenes evaluation filters it:

- "lidar_radar" (default): boxes with at least one lidar or radar (5-scan) point, the
  devkit's rule (`num_lidar_pts + num_radar_pts > 0`), the same ground truth for every
  sensor so their mAPs compare;
- "sensor": boxes with at least one point of the dumped sensor;
- "none": every box of the scene (a third of them have no lidar point at all).

Frame ids are `seed{seed:06d}` (the same scene seen by every sensor shares its id).

Detections are read off the queries as `decode` says (`detectors.infer.DECODINGS`): "topk"
keeps the `max_detections` best (query, class) pairs, so a query whose best class is a
look-alike also gives its second class, and the dump carries `det_label`; "topk_nms" (the
default) then drops a detection whose class was already detected, with a higher score,
within the class's circle-NMS radius (`detectors.nms`); "query" keeps one detection per
query, its arg-max class.

A detector with group regression heads also fills the optional multi-hypothesis arrays
`det_hyp_boxes [N, G, 9]` (final layer, one box per group head) and `det_hyp_scores [N, G]`
(summed class probabilities per group); a unified-head detector leaves them out.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from detectors.infer import detect
from detectors.model.detector import Detector
from detectors.uncertainty import attention_spread, layer_covariance
from detectors.vocab import DECODINGS, DUMP_COV_SOURCES, DUMP_FORMATS, GT_FILTERS


def frame_id(seed: int) -> str:
    """The dump token of simulated scene `seed`."""
    return f"seed{seed:06d}"


def visible_gt(frame: object, sensor: str, gt_filter: str = "lidar_radar") -> np.ndarray:
    """`[G]` bool: which ground-truth boxes of `frame` (seen by `sensor`) are evaluated."""
    from detectors.sim import render

    if gt_filter not in GT_FILTERS:
        raise ValueError(f"gt_filter must be one of {list(GT_FILTERS)}, got {gt_filter!r}")
    n_boxes = len(np.asarray(frame.scene.labels))  # type: ignore[attr-defined]
    if gt_filter == "none":
        return np.ones(n_boxes, dtype=bool)
    if gt_filter == "sensor":
        return np.asarray(frame.sensor_frame.gt_num_points) > 0  # type: ignore[attr-defined]
    count = np.zeros(n_boxes, dtype=np.int64)
    for other in ("lidar", "radar5"):
        seen = frame.sensor_frame if other == sensor else \
            render(frame.scene, other)  # type: ignore[attr-defined]
        count += np.asarray(seen.gt_num_points, dtype=np.int64)
    return count > 0


def build_dump(model: Detector, seeds: Sequence[int], cov_source: str = "layers",
               max_detections: int | None = None, gt_filter: str = "lidar_radar",
               attention_top_k: int = 6, decode: str = DECODINGS[0],
               progress: Callable[[int, int], None] | None = None):  # -> calibrators.Dump
    """Run `model` over the simulated scenes `seeds` and return a `calibrators.data._dump.Dump`.

    `max_detections` detections are kept per frame, by final-layer score (default: as many
    as the model has queries), decoded as `decode` says.
    """
    from detectors.sim import make_frame

    _check_choices(gt_filter, decode, cov_source)
    sensor = model.config.sensor
    max_detections = max_detections or model.config.n_queries
    seeds = [int(s) for s in seeds]
    parts = _Parts()
    centres = model.token_centres
    floor = torch.eye(2) * model.token_grid.cell ** 2 / 12.0
    for i, seed in enumerate(seeds):
        frame = make_frame(seed, sensor)
        points = torch.from_numpy(np.array(frame.sensor_frame.points, dtype=np.float32))
        (det,) = list(detect(model, [points], max_detections=max_detections, decode=decode))
        parts.add_detections(det, i)
        if cov_source == "layers":
            parts.covs.append(layer_covariance(det.layer_boxes.double()).numpy())
        elif cov_source == "attention":
            spread = attention_spread(det.attention.double(), centres.double(),
                                      top_k=attention_top_k)
            parts.covs.append((spread.covariance + floor.double()).numpy())
        parts.add_ground_truth(frame, visible_gt(frame, sensor, gt_filter), i)
        if progress is not None:
            progress(i + 1, len(seeds))
    return parts.dump(model, seeds, cov_source, decode)


def _check_choices(gt_filter: str, decode: str, cov_source: str) -> None:
    if gt_filter not in GT_FILTERS:
        raise ValueError(f"gt_filter must be one of {list(GT_FILTERS)}, got {gt_filter!r}")
    if decode not in DECODINGS:
        raise ValueError(f"decode must be one of {list(DECODINGS)}, got {decode!r}")
    if cov_source not in DUMP_COV_SOURCES:
        raise ValueError(f"cov_source must be one of {list(DUMP_COV_SOURCES)}, "
                         f"got {cov_source!r}")


def _cat(parts: list[np.ndarray], shape: tuple[int, ...], dtype: type) -> np.ndarray:
    return np.concatenate(parts) if parts else np.zeros((0, *shape), dtype=dtype)


@dataclass
class _Parts:
    """The dump's arrays, one part per frame."""

    det_frame: list[np.ndarray] = field(default_factory=list)
    logits: list[np.ndarray] = field(default_factory=list)
    boxes: list[np.ndarray] = field(default_factory=list)
    covs: list[np.ndarray] = field(default_factory=list)
    hyp_boxes: list[np.ndarray] = field(default_factory=list)
    hyp_scores: list[np.ndarray] = field(default_factory=list)
    labels: list[np.ndarray] = field(default_factory=list)
    gt_frame: list[np.ndarray] = field(default_factory=list)
    gt_labels: list[np.ndarray] = field(default_factory=list)
    gt_boxes: list[np.ndarray] = field(default_factory=list)

    def add_detections(self, det: Any, i: int) -> None:
        """The detections `det` of frame `i` (all but their covariance)."""
        self.labels.append(det.labels.numpy())
        self.det_frame.append(np.full(len(det.scores), i, dtype=np.int64))
        self.logits.append(det.layer_logits.numpy())
        self.boxes.append(det.layer_boxes.numpy())
        if det.hyp_boxes is not None and det.hyp_scores is not None:
            self.hyp_boxes.append(det.hyp_boxes.numpy())
            self.hyp_scores.append(det.hyp_scores.numpy())

    def add_ground_truth(self, frame: Any, keep: np.ndarray, i: int) -> None:
        """The ground-truth boxes `keep` of `frame`, frame `i`."""
        g_boxes = np.asarray(frame.scene.boxes, dtype=np.float64).reshape(-1, 9)[keep]
        self.gt_frame.append(np.full(len(g_boxes), i, dtype=np.int64))
        self.gt_labels.append(np.asarray(frame.scene.labels, dtype=np.int64).reshape(-1)[keep])
        self.gt_boxes.append(g_boxes)

    def dump(self, model: Detector, seeds: list[int], cov_source: str, decode: str):
        """The `calibrators.Dump` of the parts (empty arrays of the right shape for none)."""
        from calibrators.data import Dump

        n_layers, n_classes = model.config.n_layers, len(model.config.classes)
        n_groups = len(model.config.groups)
        grouped = model.config.head == "group"
        return Dump(
            classes=tuple(model.config.classes), score_mode="sigmoid",
            frame_ids=np.array([frame_id(s) for s in seeds]),
            det_frame=_cat(self.det_frame, (), np.int64),
            det_logits=_cat(self.logits, (n_layers, n_classes), np.float32),
            det_boxes=_cat(self.boxes, (n_layers, 9), np.float32),
            gt_frame=_cat(self.gt_frame, (), np.int64),
            gt_labels=_cat(self.gt_labels, (), np.int64),
            gt_boxes=_cat(self.gt_boxes, (9,), np.float64),
            det_cov=_cat(self.covs, (2, 2), np.float64) if cov_source != "none" else None,
            cov_dims=("x", "y"),
            det_hyp_boxes=_cat(self.hyp_boxes, (n_groups, 9), np.float32) if grouped else None,
            det_hyp_scores=_cat(self.hyp_scores, (n_groups,), np.float32) if grouped else None,
            det_label=_cat(self.labels, (), np.int64) if decode != "query" else None)


def write_dump(dump, out: str | Path, fmt: str = "npz") -> list[Path]:
    """Write `dump` as NPZ v1 (`out`) or as nuScenes JSON (`out` results + `*_gt.json`)."""
    from calibrators import io

    if fmt not in DUMP_FORMATS:
        raise ValueError(f"format must be one of {list(DUMP_FORMATS)}, got {fmt!r}")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "npz":
        io.save_dump(out, dump)
        return [out]
    gt = out.with_name(out.stem + "_gt.json")
    io.save_nuscenes(dump, out, gt)
    return [out, gt]
